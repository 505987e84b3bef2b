"""Shape checks at the public seams of the refiners and models: one line naming the tensor,
what it should be and what it is."""

from __future__ import annotations

from torch import Tensor


def check_shape(tensor: Tensor, name: str, spec: str) -> dict[str, int]:
    """Check ``tensor``'s shape against ``spec``: space-separated dimensions, each a number
    or a letter (bound on first use, the same size wherever it repeats) -> the letters'
    sizes; a ValueError such as ``starts must be [B, 7], got [4, 6]`` otherwise."""
    names = spec.split()
    sizes: dict[str, int] = {}
    fits = tensor.dim() == len(names)
    for dim, want in zip(tensor.shape, names, strict=False):
        if want.isdigit():
            fits &= dim == int(want)
        elif sizes.setdefault(want, dim) != dim:
            fits = False
    if not fits:
        raise ValueError(
            f"{name} must be [{', '.join(names)}], got [{', '.join(map(str, tensor.shape))}]"
        )
    return sizes
