"""Constructor arguments recorded once, in a base class, and shown by ``repr``.

The data module caches generated sets under a hash of ``repr(physics)`` and ``repr(dgp)``,
so a repr must show every setting that changes a simulation. :class:`RecordsInitArgs`
binds the arguments of each instance's outermost constructor call (defaults applied) into
``init_args`` and prints them: a subclass writes only its ``__init__``, never a repr.
"""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Callable
from typing import Any

from otgb.errors import InputError


class RecordsInitArgs:
    """Records the outermost ``__init__`` call's arguments in ``init_args``; ``repr`` prints them.

    Every subclass's ``__init__`` is wrapped once, when the class is created; the wrapper keeps
    the real signature and docstring (``functools.wraps``), which jsonargparse reads. Only the
    outermost call (the concrete class's constructor) is recorded, not the ``super().__init__``
    calls it makes.
    """

    init_args: dict[str, Any]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is not None and not getattr(init, "records_init_args", False):
            cls.__init__ = _recording(init)

    def __repr__(self) -> str:
        name, record = _constructor_call(self)
        args = ", ".join(f"{key}={format_value(value)}" for key, value in record.items())
        return f"{name}({args})"


def as_config(value: Any) -> Any:
    """``value`` as a config entry that jsonargparse builds again: an object that records its constructor's arguments
    as its ``class_path`` and ``init_args`` (theirs too), a list or tuple as a list, anything else as it is. A default
    written as ``lazy_instance(cls, **kwargs)`` is named as ``cls``."""
    lazy_data = getattr(value, "lazy_get_init_data", None)
    if lazy_data is not None:
        data = lazy_data().as_dict()
        return {"class_path": data["class_path"], "init_args": {k: as_config(v) for k, v in data.get("init_args", {}).items()}}
    if isinstance(value, RecordsInitArgs):
        cls = type(value)
        arguments = {key: as_config(item) for key, item in value.init_args.items()}
        return {"class_path": f"{cls.__module__}.{cls.__qualname__}", "init_args": arguments}
    if isinstance(value, (list, tuple)):
        return [as_config(item) for item in value]
    return value


def _recording(init: Callable[..., None]) -> Callable[..., None]:
    @functools.wraps(init)
    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        if "init_args" not in self.__dict__:
            object.__setattr__(self, "init_args", _bound_arguments(init, self, args, kwargs))
        init(self, *args, **kwargs)

    __init__.records_init_args = True  # type: ignore[attr-defined]
    return __init__


def _bound_arguments(init: Callable[..., None], instance: Any, args: tuple, kwargs: dict[str, Any]) -> dict[str, Any]:
    """The arguments of ``init(instance, *args, **kwargs)`` by name, defaults applied, ``**kwargs`` merged."""
    signature = inspect.signature(init)
    bound = signature.bind(instance, *args, **kwargs)
    bound.apply_defaults()
    record: dict[str, Any] = {}
    for parameter in list(signature.parameters.values())[1:]:
        value = bound.arguments[parameter.name]
        if parameter.kind is inspect.Parameter.VAR_KEYWORD:
            record.update(value)
        else:
            record[parameter.name] = value
    return record


def _constructor_call(obj: RecordsInitArgs) -> tuple[str, dict[str, Any]]:
    """The class name and the recorded arguments of ``obj``.

    A default written as jsonargparse's ``lazy_instance(cls, **kwargs)`` (so that ``--print_config``
    shows it as class_path/init_args) is an instance of a generated subclass of ``cls`` that may
    not have run ``__init__`` yet: it is named and bound as ``cls(**kwargs)``.
    """
    lazy_data = getattr(obj, "lazy_get_init_data", None)
    if lazy_data is None:
        return type(obj).__name__, obj.init_args
    data = lazy_data().as_dict()
    module, _, name = data["class_path"].rpartition(".")
    cls = getattr(importlib.import_module(module), name)
    return name, _bound_arguments(cls.__init__, obj, (), data.get("init_args", {}))


def format_value(value: Any) -> str:
    """A deterministic text of a recorded argument: lists and tuples print alike."""
    if isinstance(value, (list, tuple)):
        items = [format_value(item) for item in value]
        return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key!r}: {format_value(item)}" for key, item in value.items()) + "}"
    return repr(value)


def invalid(owner: object, name: str, value: Any, expected: str) -> InputError:
    """The error for a bad constructor argument: which class, which argument, what was given and expected."""
    return InputError(f"{type(owner).__name__}: {name}={value!r} is invalid; expected {expected}")
