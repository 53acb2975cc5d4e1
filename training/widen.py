"""Start a wider network from a trained one: Net2WiderNet (Chen, Goodfellow and Shlens,
"Net2Net: accelerating learning via knowledge transfer", ICLR 2016).

A hidden layer of width ``n`` grows to ``m > n`` by copying ``m - n`` of its units (chosen at
random) and dividing each copied unit's outgoing weights among its copies. With ReLU layers
the wider network computes exactly the same function; the optional ``noise`` then perturbs
the copies' incoming weights so that they can drift apart under training (identical copies
receive identical gradients for ever).

It works on SB3 policy state dicts, chain by chain: a chain is a stack of hidden linear layers
``prefix.0, prefix.2, ...`` (``nn.Sequential`` of Linear/ReLU) and the heads that read its last
hidden layer. SAC and TQC: the actor (``actor.latent_pi`` with heads ``actor.mu`` and
``actor.log_std``) and each critic (``critic.qf<i>``, its last linear layer the head); the target
critics use their critic's unit mapping so that critic and target stay a matched pair.
"""
from __future__ import annotations

import re

import torch


def _chains(shapes: dict[str, torch.Size]) -> list[tuple[list[str], list[str]]]:
    """``[(hidden layer prefixes, head prefixes)]`` of an SB3 SAC/TQC policy state dict, from
    its ``*.weight`` names; the critic chains are followed by their targets' (same order)."""
    chains = []
    if "actor.latent_pi.0.weight" in shapes:
        hidden = sorted({m.group(1) for k in shapes
                         if (m := re.match(r"(actor\.latent_pi\.\d+)\.weight$", k))},
                        key=lambda p: int(p.rsplit(".", 1)[1]))
        heads = [h for h in ("actor.mu", "actor.log_std") if f"{h}.weight" in shapes]
        chains.append((hidden, heads))
    for net in ("critic", "critic_target"):
        names = sorted({m.group(1) for k in shapes
                        if (m := re.match(rf"({net}\.qf\d+)\.\d+\.weight$", k))})
        for q in names:
            layers = sorted({m.group(1) for k in shapes
                             if (m := re.match(rf"({re.escape(q)}\.\d+)\.weight$", k))},
                            key=lambda p: int(p.rsplit(".", 1)[1]))
            chains.append((layers[:-1], layers[-1:]))
    return chains


def widen_state_dict(src: dict[str, torch.Tensor], dst: dict[str, torch.Tensor], *,
                     noise: float = 0.0, generator: torch.Generator | None = None
                     ) -> dict[str, torch.Tensor]:
    """``src``'s networks widened to ``dst``'s shapes (both SB3 SAC/TQC policy state dicts with
    the same chains, depths, inputs and outputs; every hidden width in ``dst`` at least
    ``src``'s). ``noise``: the copies' incoming weights and biases get Gaussian noise of this
    fraction of their layer's weight standard deviation (0: exactly ``src``'s function).
    Returns a new state dict with ``dst``'s keys and shapes."""
    if noise < 0:
        raise ValueError(f"noise: must be >= 0, got {noise}")
    if set(src) != set(dst):
        raise ValueError("widen_state_dict: source and target policies have different layers "
                         f"(only in source: {sorted(set(src) - set(dst))[:4]}, only in target: "
                         f"{sorted(set(dst) - set(src))[:4]}); they must share depth and heads")
    out = {k: v.detach().clone() for k, v in src.items()}
    # critic chain -> its hidden layers' unit maps and copy noise (the target reuses both)
    maps: dict[str, list] = {}
    for hidden, heads in _chains({k: v.shape for k, v in src.items()}):
        key = hidden[0].replace("critic_target.", "critic.")
        reuse = key in maps
        layer_maps = maps.setdefault(key, [])
        for i, layer in enumerate(hidden):
            W, b = out[f"{layer}.weight"], out[f"{layer}.bias"]
            n, m = W.shape[0], dst[f"{layer}.weight"].shape[0]
            if m < n:
                raise ValueError(f"{layer}: the target is narrower ({m}) than the source ({n}); "
                                 "only widening preserves the function")
            if not reuse:
                extra = torch.randint(n, (m - n,), generator=generator)
                s = noise * float(src[f"{layer}.weight"].std())
                layer_maps.append((torch.cat([torch.arange(n), extra]),
                                   s * torch.randn((m - n, W.shape[1]), generator=generator,
                                                   dtype=W.dtype),
                                   s * torch.randn(m - n, generator=generator, dtype=b.dtype)))
            g, dW, db = layer_maps[i]
            W, b = W[g].clone(), b[g].clone()
            W[n:] += dW
            b[n:] += db
            out[f"{layer}.weight"], out[f"{layer}.bias"] = W, b
            count = torch.bincount(g, minlength=n).to(W.dtype)[g]
            for nxt in (hidden[i + 1:i + 2] or heads):
                out[f"{nxt}.weight"] = out[f"{nxt}.weight"][:, g] / count
    for k, v in out.items():
        if v.shape != dst[k].shape:
            raise ValueError(f"{k}: widened to {tuple(v.shape)} but the target has "
                             f"{tuple(dst[k].shape)} (inputs and outputs must match)")
    return out


def widen_into(model, path, *, noise: float = 0.01, seed: int = 0) -> None:
    """Load the saved SAC/TQC model at ``path`` into ``model`` (same algorithm and spaces, hidden
    layers at least as wide), widened by :func:`widen_state_dict`. The optimizers start afresh
    (their moments have the old shapes); the entropy coefficient is the caller's to load."""
    from stable_baselines3.common.save_util import load_from_zip_file

    _, params, _ = load_from_zip_file(str(path), device="cpu", load_data=False)
    if params is None or "policy" not in params:
        raise ValueError(f"{path}: holds no policy networks")
    gen = torch.Generator().manual_seed(seed)
    new = widen_state_dict(params["policy"], model.policy.state_dict(), noise=noise,
                           generator=gen)
    model.policy.load_state_dict(new)
