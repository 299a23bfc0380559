"""Evaluation of a trained world model on held-out real data (paper Appendix J; Table 15 columns).

* :func:`reconstruction_mse` -- ``sum_k d_k mse_k / sum_k d_k`` in raw observation units over windows ``[N, T]``
  (health: ``(36 mse_imu + 16 mse_hr_features) / 52``, the mean squared error per feature).
* :func:`imagination_horizon` -- for each window of ``C + H_max`` steps the posterior is filtered over the first
  ``C`` transitions (posterior means), then the prior is rolled open loop with the *recorded* actions (prior means).
  At imagined step ``k = 1..H_max`` the reward head's prediction is compared with the real reward of that step. The
  horizon of a window is the number of imagined steps before the first step where ``|r_hat - r| > reward_tol`` or
  where the continuation head predicts a termination (``c < 0.5``) that did not happen; ``H_max`` if neither occurs.
* :func:`sample_windows` -- random windows without an episode end inside, cut from rollouts ``[E, L]``.
* :func:`seed_latents` -- posterior latents of replayed slices, the start states of imagination.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from freamer_rl.world_model.rssm import WorldModel

__all__ = ["reconstruction_mse", "imagination_horizon", "sample_windows", "seed_latents"]


@torch.no_grad()
def seed_latents(world_model: WorldModel, batch: TensorDictBase, num: int) -> TensorDict:
    """Posterior latents of replayed slices ``[N, T]`` (samples, as in training), ``num`` of them drawn at random
    from the ``N (T + 1)`` positions: ``TensorDict(deter=[num, D], stoch=[num, S])``."""
    out, _ = world_model.observe(batch)
    h = out["h"].reshape(-1, world_model.deter_dim)
    z = out["z"].reshape(-1, world_model.stoch_dim)
    idx = torch.randperm(h.shape[0])[:num]
    return TensorDict({"deter": h[idx], "stoch": z[idx]}, batch_size=[idx.numel()])


def sample_windows(traj: TensorDictBase, length: int, count: int, generator: torch.Generator) -> TensorDictBase | None:
    """``count`` random windows ``[count, length]`` of ``traj [E, L]`` without a ``done`` before their last step."""
    E, L = traj.shape
    if L < length:
        return None
    done = traj.get(("next", "done")).reshape(E, L).int()
    # window [s, s + length) is valid when no done in [s, s + length - 1)
    csum = torch.cat([torch.zeros(E, 1, dtype=torch.long), done.cumsum(-1)], dim=-1)  # [E, L + 1]
    starts = torch.arange(L - length + 1)
    bad = (csum[:, starts + length - 1] - csum[:, starts]) > 0  # [E, S]
    valid = (~bad).nonzero()
    if valid.shape[0] == 0:
        return None
    pick = valid[torch.randint(valid.shape[0], (count,), generator=generator)]
    idx = pick[:, 1:2] + torch.arange(length)  # [count, length]
    return traj[pick[:, 0:1].expand_as(idx), idx]


@torch.no_grad()
def reconstruction_mse(world_model: WorldModel, windows: TensorDictBase) -> dict[str, float]:
    """Raw-unit reconstruction MSE on ``windows [N, T]``: per key and ``recon_mse = sum_k d_k mse_k / sum_k d_k``."""
    world_model.eval()
    losses = world_model.loss(windows)
    out = {}
    num = 0.0
    for k, d in world_model.obs_dims.items():
        name = k if isinstance(k, str) else "_".join(k)
        v = float(losses[f"mse_{name}"])
        out[f"recon_mse_{name}"] = v
        num += d * v
    out["recon_mse"] = num / sum(world_model.obs_dims.values())
    return out


@torch.no_grad()
def imagination_horizon(
    world_model: WorldModel, windows: TensorDictBase, context: int, reward_tol: float
) -> torch.Tensor:
    """Open-loop reward-prediction horizon of each window (module docstring): ``windows [N, C + H_max]`` ->
    ``[N]`` float (number of imagined steps before the first reward error ``> reward_tol`` or false predicted
    termination; ``H_max`` when none); definition in the module docstring."""
    world_model.eval()
    N, L = windows.shape
    H = L - context
    if context < 1 or H < 1:
        raise ValueError(
            f"imagination_horizon: need context >= 1 and a window longer than it; got context {context}, window {L}"
        )
    out, _ = world_model.observe(windows[:, :context], sample=False)
    h, z = out["h"][:, -1], out["post_mean"][:, -1]
    actions = world_model.action_to_onehot(windows.get("action")[:, context:], 2)
    real_r = windows.get(("next", "reward")).reshape(N, L)[:, context:]
    real_term = windows.get(("next", "terminated")).reshape(N, L)[:, context:]
    fail = torch.zeros(N, H, dtype=torch.bool)
    for k in range(H):
        h, _, z = world_model.rssm.imagine_step(h, z, actions[:, k], sample=False)
        feat = world_model.features(h, z)
        r_hat = world_model.reward_head(feat).squeeze(-1)
        pred_term = torch.sigmoid(world_model.continue_head(feat).squeeze(-1)) < 0.5
        fail[:, k] = ((r_hat - real_r[:, k]).abs() > reward_tol) | (pred_term & ~real_term[:, k])
    any_fail = fail.any(-1)
    first = fail.float().argmax(-1)
    return torch.where(any_fail, first, torch.full_like(first, H)).float()
