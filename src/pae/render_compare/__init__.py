"""Render-and-compare pose refinement against a scene model learned from the train images,
callable without a Trainer:

- :func:`refine`: from any starts (an APR's estimates), the refined poses through the gate;
- :func:`calibrate`: the gate, the search's first steps and the scene decision chosen on
  validation queries with their true poses, for :func:`refine` to apply at test;
- :func:`calibrate_any_start`: the same for another APR's starts, whose error scale is
  unknown: chosen on validation starts at every scale;
- :class:`Queries`: the queries' images, intrinsics and scenes (and a multi-scene APR's
  poses and logits, the queries at their match width); :class:`Validation`: val queries
  with their starts and true poses; :class:`CalibrationOptions`: what :func:`calibrate`
  chooses, under one objective;
- with the queries' sequences (``sequences=Sequences(ids, options)``),
  :class:`SequenceOptions` say how both use the frame order of the walks
  (:mod:`pae.render_compare.sequences`).

The refiner itself is :class:`pae.render_compare.refiner.RenderCompareRefiner`, its settings
:class:`pae.render_compare.settings.RenderCompareSettings`."""

from __future__ import annotations

from pae.render_compare.api import (
    Queries,
    Refinement,
    Settings,
    Validation,
    build_refiner,
    calibrate,
    calibrate_any_start,
    refine,
)
from pae.render_compare.calibration import AnyStartOptions, Calibration, CalibrationOptions
from pae.render_compare.gate import ACCEPT_ALL, RenderCompareResult
from pae.render_compare.sequences import SequenceOptions, Sequences
from pae.render_compare.settings import RenderCompareSettings

__all__ = [
    "ACCEPT_ALL",
    "AnyStartOptions",
    "Calibration",
    "CalibrationOptions",
    "Queries",
    "Refinement",
    "RenderCompareResult",
    "RenderCompareSettings",
    "SequenceOptions",
    "Sequences",
    "Settings",
    "Validation",
    "build_refiner",
    "calibrate",
    "calibrate_any_start",
    "refine",
]
