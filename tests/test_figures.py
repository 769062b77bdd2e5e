"""Every kind of figure the project writes, opened: axis labels, a title saying what and at which step, a legend or a
colour bar, a readable size, and shared scales where a reader compares panels by eye."""

from dataclasses import replace

import matplotlib.image
import pytest
import torch

from otgb.analysis.figures import (
    DPI,
    MIN_WIDTH_PX,
    close,
    components_figure,
    disagreement_figure,
    distribution_figure,
    frames_figure,
    save,
    space_time_figure,
    trajectory_figure,
)
from otgb.data import generate_measured
from otgb.discovery.locate import locate
from otgb.discovery.record import Discovery
from otgb.discovery.report import disagreement_panels
from otgb.physics import AdvectionDiffusion, Constant, Pendulum, ReactionDiffusion, ViscousFriction

STEP = 1234


def _pendulum_rows(n=4):
    pendulum = Pendulum()
    measured = generate_measured(pendulum.with_hidden_effect([ViscousFriction(Constant(1.2))]), n, 0)["y"]
    simulated = generate_measured(pendulum, n, 0)["y"]
    theta = torch.full((n, 1), 2.0)
    return pendulum, {"x": simulated, "y": measured[:, None], "theta": theta}, measured[:, None] * 1.01


def _fields(physics, n=2):
    y = generate_measured(physics, n, 0)["y"][:, :, 0]
    return {"measured": y, "generated": 1.01 * y, "f_p": 0.9 * y}, torch.ones(n, len(physics.theta_names))


def _components():
    t = torch.linspace(0, 1, 10)
    values = torch.linspace(0.1, 0.2, 10)
    return {
        "times": t, "time_label": "t (s)", "traj_err": values, "traj_err_fp": 3 * values, "traj_err_kind": "abs_err",
        "func_err": values, "func_err_fp": 2 * values,
        "func_err_unavailable": None, "f_p_abs": values, "f_phi_abs": values / 3, "summary": {"correction_share": 0.25},
    }  # fmt: skip


def _figures():
    pendulum, rows, y_hat = _pendulum_rows(8)
    measured, simulated = rows["y"][:, 0], rows["x"]
    advdiff, reactdiff = AdvectionDiffusion(), ReactionDiffusion()
    fields_1d, theta_1d = _fields(advdiff)
    fields_2d, theta_2d = _fields(reactdiff)
    ode_map = locate(measured, simulated, pendulum.observation_times(), pendulum.observed, n_permutations=99)
    field_y = generate_measured(advdiff, 40, 0)["y"]
    field_map = locate(field_y, 1.05 * field_y, advdiff.observation_times(), advdiff.observed, n_permutations=99)
    return {
        "trajectories": trajectory_figure(rows, y_hat, pendulum, 0, STEP),
        "distributions": distribution_figure(
            {"measured": measured, "f_p": simulated}, pendulum.observation_times(),
            [pendulum.axis_label(name) for name in pendulum.observed], STEP, pendulum.axis_label("t"),
        ),
        "fields 1-D": space_time_figure(fields_1d, theta_1d, advdiff, "T", STEP),
        "fields 2-D": frames_figure(fields_2d, theta_2d, reactdiff, [0, 5, 14], "u", STEP),
        "components": components_figure(_components(), STEP),
        "components, no true field": components_figure(
            {**_components(), "func_err": None, "func_err_unavailable": "the measurements come from a file"}, STEP
        ),
        "disagreement, ODE": disagreement_figure([(ode_map, "before"), (ode_map, "after")], pendulum.axis_label("t")),
        "disagreement, field": disagreement_figure([(field_map, "before"), (field_map, "after")]),
    }  # fmt: skip


@pytest.fixture(scope="module")
def figures():
    drawn = _figures()
    yield drawn
    for figure in drawn.values():
        close(figure)


def _is_colorbar(ax) -> bool:
    return hasattr(ax, "_colorbar") or ax.get_label() == "<colorbar>"


def test_every_figure_has_axis_labels_a_title_and_a_legend_or_colour_bar(figures):
    for kind, figure in figures.items():
        panels = [ax for ax in figure.axes if ax.axison and not _is_colorbar(ax)]
        assert panels, kind
        for ax in panels:
            assert ax.get_xlabel() and ax.get_ylabel(), f"{kind}: panel {ax.get_title()!r} lacks an axis label"
        assert figure._suptitle is not None and figure._suptitle.get_text(), f"{kind}: no title"
        keys = any(ax.get_legend() is not None for ax in panels) or bool(figure.legends)
        keys = keys or any(_is_colorbar(ax) for ax in figure.axes)
        assert keys, f"{kind}: neither a legend nor a colour bar"
        for ax in figure.axes:
            if _is_colorbar(ax):
                assert ax.get_ylabel() or ax.get_xlabel(), f"{kind}: a colour bar without a label"


def test_axes_give_the_units_the_model_declares(figures):
    """The pendulum declares seconds, radians and rad/s; the fields declare none, so their axes carry names alone."""
    for kind in ("trajectories", "distributions", "components", "disagreement, ODE", "fields 1-D"):
        labels = {ax.get_xlabel() for ax in figures[kind].axes if ax.axison and not _is_colorbar(ax)}
        assert labels == ({"t"} if kind == "fields 1-D" else {"t (s)"}), (kind, labels)
    first = figures["trajectories"].axes[0]
    assert first.get_ylabel() == "angle (rad)" and first.get_title() == "omega=2 rad/s", first.get_title()
    assert figures["distributions"].axes[0].get_ylabel() == "angle (rad)"


def test_titles_fit_inside_their_figures(figures):
    for kind, figure in figures.items():
        figure.canvas.draw()
        box = figure._suptitle.get_window_extent()
        assert box.x0 >= 0 and box.x1 <= figure.bbox.width, f"{kind}: the title is cut at the figure's edges"


def test_training_figures_say_at_which_step(figures):
    for kind in ("trajectories", "distributions", "fields 1-D", "fields 2-D", "components"):
        assert f"training step {STEP}" in figures[kind]._suptitle.get_text(), kind


def test_figures_are_saved_readable(figures, tmp_path):
    for kind, figure in figures.items():
        path = tmp_path / f"{kind}.png"
        save(figure, path)
        height, width = matplotlib.image.imread(path).shape[:2]
        assert width >= MIN_WIDTH_PX, f"{kind}: {width} px wide"
    assert DPI >= 150


def test_panels_compared_by_eye_share_one_scale(figures):
    for kind in ("trajectories", "disagreement, ODE"):
        limits = {ax.get_ylim() for ax in figures[kind].axes if ax.axison and not _is_colorbar(ax)}
        assert len(limits) == 1, f"{kind}: panels on different y scales {limits}"
    images = [ax.images[0] for ax in figures["disagreement, field"].axes if ax.images]
    assert len({image.norm.vmax for image in images}) == 1, "before and after heatmaps on one colour scale"


def test_a_disagreement_map_says_its_sizes_and_lists_significant_cells_only_where_there_are_some():
    pendulum, rows, _ = _pendulum_rows(40)
    measured = rows["y"][:, 0]
    same = locate(measured, measured.clone(), pendulum.observation_times(), pendulum.observed, n_permutations=99)
    differ = locate(measured, rows["x"], pendulum.observation_times(), pendulum.observed, n_permutations=99)
    assert same.sizes == (len(measured), len(measured)) and not same.any_significant
    figure = disagreement_figure([(differ, "before"), (same, "after")])
    before, after = ([t.get_text() for t in ax.get_legend().get_texts()] for ax in figure.axes)
    assert differ.significant.any() and any(text.endswith(": significant") for text in before), before
    assert not any(text.endswith(": significant") for text in after), after
    titles = [ax.get_title().splitlines()[-1] for ax in figure.axes]
    assert differ.whole_significant and titles[0] == f"whole trajectories: differ (permutation p = {differ.whole_pvalue:.2g})"
    assert titles[1] == f"whole trajectories: no difference seen (permutation p = {same.whole_pvalue:.2g})", titles
    dips = replace(same, statistic=same.statistic - 0.01)  # an unbiased distance below 0 on the first panel only
    for ax in disagreement_figure([(dips, "before"), (differ, "after")]).axes:
        assert ax.get_ylim()[0] <= float(dips.statistic.min()), "every panel shows every value on the shared scale"


def test_discovery_draws_before_and_after_on_the_same_test_trajectories():
    """The figure that should show the gap shrink: f_p and the augmented physics against the same test part, on the
    training part's scale, with numbers on every panel."""
    pendulum, rows, _ = _pendulum_rows(40)
    measured, times = rows["y"][:, 0], pendulum.observation_times()
    train = locate(measured, rows["x"], times, pendulum.observed, n_permutations=99)
    test = locate(measured[:20], rows["x"][:20], times, pendulum.observed, n_permutations=99)
    after = locate(measured[:20], measured[20:], times, pendulum.observed, n_permutations=99)
    panels = disagreement_panels(Discovery(before=train, sentence_before="", before_on_test=test, after=after))
    assert [title for _, title in panels] == [
        "f_p vs measured: the training part, 40 trajectories",
        "before: f_p vs measured, the test part, 20 trajectories",
        "after: augmented vs measured, the test part, 20 trajectories",
    ]
    figure = disagreement_figure(panels)
    assert len(figure.axes) == 3 and len({ax.get_ylim() for ax in figure.axes}) == 1, "one scale for all panels"
    assert all(ax.yaxis.get_ticklabels()[1].get_visible() for ax in figure.axes), "numbers on every panel"
    close(figure)
