"""The ``raw`` encoding (6 features, ablations only): (wi, wo) as they are.

It is NOT reciprocal -- the network sees the order of the pair -- and it is there to
measure what the symmetric encodings buy (the ablation "symmetric encoding vs raw
input").  It can represent anisotropic BRDFs, so everything that depends on the encoding
(the albedo table, the furnace grid) treats it as anisotropic; it has no grid axes.
"""

from __future__ import annotations

import torch


def features(wi: torch.Tensor, wo: torch.Tensor, peak: str = "u_h") -> torch.Tensor:
    """(..., 3), (..., 3) -> (..., 6): wi then wo (``peak`` is not used)."""
    return torch.cat([wi, wo], -1)
