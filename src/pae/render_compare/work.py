"""What a render-and-compare refiner did: the work its kernels ran and the time each phase
took, for ``pae-bench``'s MFLOP per query and roofline fraction."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from pae.render_compare.kernels.numba_score import FLOPS_PER_POINT_SCORE
from pae.render_compare.kernels.reference import FLOPS_PER_POINT_STEP


@dataclass
class RenderCompareWork:
    """Counts since the refiner was made: score_points (reference points × candidates
    scored), polish_point_steps (reference points × hypotheses × polish steps),
    rendered_rays (reference renderings' pixels); seconds spent scoring, polishing and
    rendering."""

    score_points: int = 0
    polish_point_steps: int = 0
    rendered_rays: int = 0
    score_s: float = 0.0
    polish_s: float = 0.0
    render_s: float = 0.0

    @property
    def kernel_mflop(self) -> float:
        """Floating-point work of the score and polish kernels (MFLOP), counted per point."""
        return (
            self.score_points * FLOPS_PER_POINT_SCORE
            + self.polish_point_steps * FLOPS_PER_POINT_STEP
        ) / 1e6

    @contextmanager
    def timed(self, phase: str) -> Iterator[None]:
        """Add the block's wall time to ``{phase}_s``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            setattr(self, f"{phase}_s", getattr(self, f"{phase}_s") + time.perf_counter() - start)
