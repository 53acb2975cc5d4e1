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

Inputs can grow too: where the target's first layers read more features than the source's, the
extra features are taken to be appended at the end of the flattened observation (for SB3's
``CombinedExtractor`` over a ``Dict`` space, whose keys Gymnasium sorts, a new last entry of
``observation``) and get zero weights, so the function ignores them until training moves them
(a new observation entry for a trained agent: ``ReachConfig.observe_stiffness``). The critics
read ``[features, action]``: their new columns go between the two, at the actor's old input
count.
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


def _feature_count(sd: dict[str, torch.Tensor]) -> int | None:
    """The number of observation features the networks read: the actor's input count (the
    critics read them followed by the action); None without an actor."""
    w = sd.get("actor.latent_pi.0.weight")
    return None if w is None else int(w.shape[1])


def _insert_zero_columns(W: torch.Tensor, at: int, n: int) -> torch.Tensor:
    """``W (out, in)`` with ``n`` zero columns inserted before column ``at``."""
    return torch.cat([W[:, :at], W.new_zeros(W.shape[0], n), W[:, at:]], 1)


def widen_state_dict(src: dict[str, torch.Tensor], dst: dict[str, torch.Tensor], *,
                     noise: float = 0.0, generator: torch.Generator | None = None
                     ) -> dict[str, torch.Tensor]:
    """``src``'s networks widened to ``dst``'s shapes (both SB3 SAC/TQC policy state dicts with
    the same chains, depths and outputs; every hidden width and the input count in ``dst`` at
    least ``src``'s, extra inputs appended last with zero weights). ``noise``: the copies'
    incoming weights and biases get Gaussian noise of this fraction of their layer's weight
    standard deviation (0: exactly ``src``'s function).
    Returns a new state dict with ``dst``'s keys and shapes."""
    if noise < 0:
        raise ValueError(f"noise: must be >= 0, got {noise}")
    if set(src) != set(dst):
        raise ValueError("widen_state_dict: source and target policies have different layers "
                         f"(only in source: {sorted(set(src) - set(dst))[:4]}, only in target: "
                         f"{sorted(set(dst) - set(src))[:4]}); they must share depth and heads")
    out = {k: v.detach().clone() for k, v in src.items()}
    chains = _chains({k: v.shape for k, v in src.items()})
    at = _feature_count(src)
    for hidden, _ in chains:
        k = f"{hidden[0]}.weight"      # the layer that reads the inputs
        extra = dst[k].shape[1] - out[k].shape[1]
        if extra < 0:
            raise ValueError(f"{hidden[0]}: the target reads fewer inputs ({dst[k].shape[1]}) "
                             f"than the source ({out[k].shape[1]}); only appended inputs keep "
                             "the function")
        if extra:
            if at is None:
                raise ValueError("inputs grow but the policy has no actor to tell where its "
                                 "features end")
            out[k] = _insert_zero_columns(out[k], at, extra)
    # critic chain -> its hidden layers' unit maps and copy noise (the target reuses both)
    maps: dict[str, list] = {}
    for hidden, heads in chains:
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
    """Load the saved SAC/TQC model at ``path`` into ``model`` (same algorithm and action space,
    hidden layers at least as wide, observations with the same entries or more appended last),
    widened by :func:`widen_state_dict`. Where only inputs were appended (every hidden width
    the same) the optimizers keep their Adam moments, zero for the new weights, so the first
    updates are as small as a plain fine-tune's; a wider network's optimizers start afresh
    (their moments have the old shapes). The entropy coefficient is the caller's to load."""
    from stable_baselines3.common.save_util import load_from_zip_file

    _, params, _ = load_from_zip_file(str(path), device="cpu", load_data=False)
    if params is None or "policy" not in params:
        raise ValueError(f"{path}: holds no policy networks")
    gen = torch.Generator().manual_seed(seed)
    dst = model.policy.state_dict()
    new = widen_state_dict(params["policy"], dst, noise=noise, generator=gen)
    model.policy.load_state_dict(new)
    same_width = all(v.shape[0] == dst[k].shape[0] for k, v in params["policy"].items())
    if same_width:
        at = _feature_count(params["policy"])
        for name in ("actor.optimizer", "critic.optimizer"):
            if name in params:
                _load_padded_optimizer(model, name, params[name], at)


def _load_padded_optimizer(model, name: str, state: dict, at: int | None) -> None:
    """Load an Adam state dict saved for the narrower-input networks into ``model``'s optimizer
    ``name``: moments of the inserted input columns (before column ``at``, as in
    :func:`widen_state_dict`) start at zero."""
    obj = model
    for part in name.split("."):
        obj = getattr(obj, part)
    params = [p for g in obj.param_groups for p in g["params"]]
    state = {"state": {i: dict(s) for i, s in state["state"].items()},
             "param_groups": state["param_groups"]}
    for i, s in state["state"].items():
        shape = params[int(i)].shape
        for key in ("exp_avg", "exp_avg_sq"):
            m = s.get(key)
            if m is not None and m.shape != shape:
                if (at is None or m.ndim != 2 or m.shape[0] != shape[0]
                        or m.shape[1] > shape[1]):
                    raise ValueError(f"{name}: parameter {i} moments {tuple(m.shape)} do not "
                                     f"extend to {tuple(shape)} by appended inputs")
                s[key] = _insert_zero_columns(m, at, shape[1] - m.shape[1])
    obj.load_state_dict(state)
