"""Render-and-compare's kernels: each fast kernel (numba, CPU) beside its tensor reference
(any torch device), tested equal.

- :mod:`pae.render_compare.kernels.reference`: the score and the Levenberg–Marquardt polish
  with tensor operations, their constants and the polish's inputs;
- :mod:`pae.render_compare.kernels.numba_score`: the score, one compiled pass per candidate;
- :mod:`pae.render_compare.kernels.numba_polish`: the polish, one compiled loop per query.

The engine (``auto|numba|torch``, :data:`pae.core.compiled.ENGINES`) chooses between them."""
