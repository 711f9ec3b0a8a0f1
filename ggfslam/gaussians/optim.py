"""Adam over a map whose per-anchor tensors change size: moment estimates follow the kept rows."""
from __future__ import annotations

import torch
from torch import nn


def make_adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam (fused on CPU: ~3x cheaper per step than the default loop) over named parameter groups."""
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


def replace_param(opt: torch.optim.Optimizer, old: nn.Parameter, new: nn.Parameter,
                  keep: torch.Tensor | None = None, n_added: int = 0) -> None:
    """Swap ``old`` for ``new`` in ``opt``: state rows ``keep`` (bool [A] or None = all) are kept and
    ``n_added`` zero rows appended, matching how ``new`` was built from ``old``."""
    for group in opt.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
    state = opt.state.pop(old, None)
    if not state:
        return
    for key in ("exp_avg", "exp_avg_sq"):
        s = state[key]
        if keep is not None:
            s = s[keep]
        if n_added:
            s = torch.cat([s, s.new_zeros((n_added,) + tuple(s.shape[1:]))])
        state[key] = s.contiguous()
    opt.state[new] = state
