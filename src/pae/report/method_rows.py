"""The rows of the results tables: the methods a run's figures hold, in table order, and the
marks of audits (they read the evaluated split's labels) and bounds (they know the true
scene). Read by pae.report.tables and pae.report.seed_stats alike."""

from __future__ import annotations

from collections.abc import Mapping

METHOD_ORDER = (
    "teacher",
    "student",
    "student_gt",
    "refined",
    "knn_mean",
    "vrpr",
    "rpr_image",
    "rpr_reference",
    "iapr_1",
    "iapr_2",
    "iapr_3",
    "guess_initial",
    "guess_refined",
    "refined_test_store",
    "knn_mean_test_store",
    "guess_refined_test_store",
    "rpr_image_test_store",
    "rpr_reference_test_store",
    "render_compare",
    "render_compare_oracle",
    "mean_pose",
)
"""Row order of the results tables; other methods (refinement alternatives) follow
``refined`` and ``knn_mean`` in the order of their keys."""


TEST_STORE_SUFFIX = "_test_store"
"""Methods whose name ends so read the evaluated split's labels (they retrieve among its own
poses, or by its true poses): audits."""


ORACLE_SUFFIX = "_oracle"
"""Methods whose name ends so know what no method may (the true scene): bounds."""


GROUND_TRUTH_METHODS = ("student_gt", "guess_initial", "guess_refined")
"""Methods (and their ``_test_store`` audits) that start from the true pose: checks of the
PAE and of refinement, not localisation methods."""


def starts_from_truth(method: str) -> bool:
    """Whether ``method`` starts from the true pose (``GROUND_TRUTH_METHODS``)."""
    return method.removesuffix(TEST_STORE_SUFFIX) in GROUND_TRUTH_METHODS


def marked(method: str) -> str:
    """A table row's label: ``*`` after audits, ``†`` after bounds, ``‡`` after checks that
    start from the true pose."""
    label = method
    if method.endswith(TEST_STORE_SUFFIX):
        label += " *"
    elif method.endswith(ORACLE_SUFFIX):
        label += " †"
    return label + " ‡" if starts_from_truth(method) else label


def table_methods(metrics: Mapping[str, float], split: str = "test") -> list[str]:
    """Methods with a ``{split}/{method}/pos_median_m`` figure, in table order."""
    found = list(
        dict.fromkeys(
            key.split("/")[1]
            for key in metrics
            if key.startswith(f"{split}/") and key.endswith("/pos_median_m") and key.count("/") == 2
        )
    )
    known = [m for m in METHOD_ORDER if m in found]
    extra = [m for m in found if m not in METHOD_ORDER]
    if not extra:
        return known
    anchors = [known.index(m) + 1 for m in ("refined", "knn_mean") if m in known]
    cut = max(anchors, default=len(known))
    return known[:cut] + extra + known[cut:]
