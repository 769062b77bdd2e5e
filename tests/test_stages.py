"""Where a discovery run's time goes (otgb.discovery.stages): each stage's own seconds, on a clock the test sets."""

import pytest

from otgb.discovery import stages
from otgb.discovery.stages import OTHER, Stopwatch, markdown_rows, stage


@pytest.fixture
def clock(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(stages.time, "perf_counter", lambda: now[0])
    return now


def test_a_stage_inside_another_is_counted_once_as_itself_and_the_rest_is_other(clock):
    @stage("fit")  # as the workflow's steps mark themselves
    def fit(seconds: float) -> None:
        clock[0] += seconds

    with Stopwatch() as watch:
        clock[0] += 4.0  # set-up, in no stage
        with stage("search"):
            clock[0] += 2.0
            fit(3.0)
            clock[0] += 1.0
        fit(0.5)
    assert watch.total == 10.5 and watch.seconds == {"search": 3.0, "fit": 3.5, OTHER: 4.0}
    assert watch.calls == {"search": 1, "fit": 2}
    rows = watch.record()["stages"]
    assert [r["stage"] for r in rows] == ["fit", "search", OTHER], "the longest first, other last"
    assert sum(r["share"] for r in rows) == pytest.approx(1.0)
    table = markdown_rows(watch.record())
    assert "| fit | 3.5 | 33.3% | 2 |" in table and "| other | 4.0 | 38.1% | - |" in table


def test_outside_a_stopwatch_a_stage_times_nothing_and_an_error_closes_it(clock):
    with stage("alone"):
        clock[0] += 1.0
    with Stopwatch() as watch:
        with pytest.raises(ValueError), stage("failing"):
            clock[0] += 2.0
            raise ValueError("a diverging fit")
        clock[0] += 1.0
    assert watch.seconds == {"failing": 2.0, OTHER: 1.0}, "the time after the error is no stage's"
    assert markdown_rows(None) == []
