"""The sentence on the augmented physics against the test part (report.json's ``locate.sentence_after``): what the
disagreement map sees, beside the same map of f_p alone, and, where the map and the gap table's C2ST disagree, which
one sees a difference and why the other need not.

The two judges look at different things:

- the map (:mod:`otgb.discovery.locate`): energy-distance permutation tests per cell (time step, component, region)
  at a false discovery rate, and one between whole z-scored trajectories, each at its share of alpha;
- the C2ST (:mod:`otgb.metrics.c2st`): a classifier trained on whole trajectories, scored on folds it did not see.

A classifier can learn a combination of values, such as how a trajectory's steps go together (a coefficient that
differs between trajectories, a phase), that no single energy distance reaches at its corrected level; a difference
confined to a few cells shows in the map's tests of those cells and is diluted in a classifier of whole trajectories.
"""

from __future__ import annotations

from otgb.discovery.locate import DisagreementMap, describe
from otgb.discovery.record import Discovery
from otgb.discovery.verify import c2st_numbers, c2st_tells_apart


def sentence_after(result: Discovery) -> str:
    """The sentence on the augmented physics against the test part: its disagreement map; where the map and the gap
    table's C2ST disagree, which sees a difference and why the other does not (:func:`judges_disagree`); the same map
    of f_p alone (:func:`beside_f_p`); the paired check."""
    sentence = describe(result.after, b_name="augmented-physics") + " (on the test part, which no fit saw)"
    sentence += judges_disagree(result.after, result.gap)
    sentence += beside_f_p(result.before_on_test)
    return sentence + (f"; {result.paired_after.sentence()}" if result.paired_after is not None else "")


def judges_disagree(after: DisagreementMap, gap: dict[str, dict[str, float]]) -> str:
    """Where exactly one of the map and the C2ST tells the augmented physics from the test part: which, with its
    numbers, and why the other need not see it; "" where they agree (or the C2ST has no figure)."""
    told, numbers = c2st_tells_apart(gap, "augmented"), c2st_numbers(gap, "augmented")
    if not after.any_significant and told:
        return (
            f"; but the gap table's C2ST tells the augmented physics from the measurements ({told}): a difference "
            f"remains that the map does not see (its whole-trajectory test: p = {after.whole_pvalue:.2g} at level "
            f"{after.whole_level:.3g}): a classifier of whole trajectories can learn a combination of values, such as "
            "how a trajectory's steps go together, that no single energy distance reaches at its corrected level"
        )
    if after.any_significant and not told and numbers:
        cells = int(after.significant.sum())
        where = f"in {cells} of {after.significant.numel()} cells" if cells else "in the whole-trajectory test alone"
        return (
            f"; the gap table's C2ST does not tell them apart ({numbers}): the map's difference lies {where}, which "
            "a classifier of whole trajectories dilutes among the rest of each trajectory"
        )
    return ""


def beside_f_p(before_on_test: DisagreementMap) -> str:
    """The same tests of f_p alone on the same test part, for the sentence on the augmented physics: an agreement
    after the fix means something only where f_p alone disagrees with these trajectories."""
    if not before_on_test.any_significant:
        return "; nor between f_p alone and them, so this agreement alone does not show what the fix changed"
    cells = int(before_on_test.significant.sum())
    if cells:
        where = f"in {cells} of {before_on_test.significant.numel()} cells"
    else:
        where = "as whole trajectories" if before_on_test.whole_significant else "on their recorded inputs"
    return f"; f_p alone, tested the same way, differs from them {where}"
