"""Average the weights of several fine-tunes of one model: "model soups" (Wortsman et al.,
"Model soups: averaging weights of multiple fine-tuned models improves accuracy without
increasing inference time", ICML 2022).

Fine-tunes that start from the same trained network at a small learning rate tend to stay in
one basin of the loss, where the average of their weights is itself a good network and often
a better one than each of them. The soup costs no training: only evaluations.

    python -m training.soup --out runs/soup/uniform.zip A.zip B.zip C.zip
    python -m training.soup --out runs/soup/greedy.zip --greedy --seed 20000 --episodes 500 \
        A.zip B.zip C.zip          # ingredients ranked and kept on the selection goals

Every ingredient must have the same algorithm and the same network shapes (a ``KeyError`` or
``ValueError`` names the first layer that differs). The soup's ``.zip`` is the first
ingredient's with its policy parameters (actor, critics and target critics) replaced by the
weighted mean; its optimizer states and entropy coefficient stay the first ingredient's.
Its sibling ``.json`` is the metadata of ``--like`` (default: the first ingredient with a
sibling ``.json``) plus a ``soup`` entry listing the ingredients and weights.

Greedy soup (the paper's Recipe 1): the ingredients are scored alone on the selection goals
and sorted best first; the soup starts from the best, and each next ingredient stays in if the
soup's score does not get worse. Two objectives (``--objective``, :data:`OBJECTIVES`):

* ``success`` (default): success within 1 mm, higher is better (ranking ties: fewer snaps);
* ``targets``: the worse of the two target ratios, ``T = max(miss / (1 - target_success),
  snaps / target_snaps)``, lower is better (ranking ties: higher success). ``T <= 1`` exactly
  when both targets are met (defaults: success >= 0.90 within 1 mm, snaps <= 1 %), so a soup
  is kept only if it does not move further from the target it misses most.

``--known-scores FILE`` (a JSON object ``{model path: [success, snap rate]}``, e.g. an earlier
run's ``.scores.json``) skips re-scoring ingredients already scored on the same selection goals:
the evaluation is deterministic, so a score taken once holds.
"""
from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

__all__ = ["average_state_dicts", "make_soup", "greedy_soup", "target_ratio", "OBJECTIVES",
           "main"]


def average_state_dicts(dicts: Sequence[dict[str, torch.Tensor]],
                        weights: Sequence[float] | None = None) -> dict[str, torch.Tensor]:
    """The weighted mean of state dicts with the same keys and shapes (``weights``: one
    positive number per dict, normalized to sum 1; default equal). Integer entries (counters)
    must agree and are copied from the first."""
    if not dicts:
        raise ValueError("average_state_dicts: give at least one state dict")
    w = torch.ones(len(dicts), dtype=torch.float64) if weights is None else \
        torch.as_tensor(weights, dtype=torch.float64)
    if w.shape != (len(dicts),) or not bool(torch.isfinite(w).all()) or bool((w <= 0).any()):
        raise ValueError(f"weights: need {len(dicts)} finite positive numbers, got "
                         f"{list(weights) if weights is not None else None}")
    w = w / w.sum()
    keys = list(dicts[0])
    for i, d in enumerate(dicts[1:], 1):
        if set(d) != set(keys):
            diff = sorted(set(d) ^ set(keys))
            raise KeyError(f"state dict {i} has other layers than the first: {diff[:4]}")
    out = {}
    for k in keys:
        first = dicts[0][k]
        for i, d in enumerate(dicts[1:], 1):
            if d[k].shape != first.shape:
                raise ValueError(f"{k}: state dict {i} has shape {tuple(d[k].shape)}, the first "
                                 f"{tuple(first.shape)}; a soup needs one architecture")
        if first.is_floating_point():
            acc = sum(wi * d[k].detach().to(torch.float64) for wi, d in zip(w, dicts, strict=True))
            out[k] = acc.to(first.dtype)
        else:
            if any(not torch.equal(d[k], first) for d in dicts[1:]):
                raise ValueError(f"{k}: integer entry differs between state dicts")
            out[k] = first.clone()
    return out


def _policy_params(path: Path) -> dict[str, torch.Tensor]:
    from stable_baselines3.common.save_util import load_from_zip_file

    _, params, _ = load_from_zip_file(str(path), device="cpu", load_data=False)
    if params is None or "policy" not in params:
        raise ValueError(f"{path}: not an SB3 model (no policy networks in the archive)")
    return params["policy"]


def _meta_source(paths: Sequence[Path], like: Path | None) -> Path:
    if like is not None:
        if not like.with_suffix(".json").exists():
            raise ValueError(f"--like {like}: no {like.with_suffix('.json').name} beside it")
        return like
    for p in paths:
        if p.with_suffix(".json").exists():
            return p
    raise ValueError("no ingredient has a sibling .json (algo, env id, env kwargs); name a model "
                     "that does with --like")


def make_soup(paths: Sequence[str | Path], out: str | Path, *,
              weights: Sequence[float] | None = None, like: str | Path | None = None) -> Path:
    """Write the soup of the SB3 models at ``paths`` to ``out`` (``.zip``) with its sibling
    ``.json`` (see the module docstring). Returns ``out``."""
    paths = [Path(p) for p in paths]
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"ingredient {p}: no such file")
    out = Path(out).with_suffix(".zip")
    out.parent.mkdir(parents=True, exist_ok=True)
    meta_from = _meta_source(paths, Path(like) if like is not None else None)
    meta = json.loads(meta_from.with_suffix(".json").read_text())
    soup = average_state_dicts([_policy_params(p) for p in paths], weights)
    buf = io.BytesIO()
    torch.save(soup, buf)
    # write beside the target then move, so a reader never sees half an archive
    with tempfile.NamedTemporaryFile(dir=out.parent, suffix=".zip", delete=False) as tmp:
        tmp_path = Path(tmp.name)
    with zipfile.ZipFile(paths[0]) as src, zipfile.ZipFile(tmp_path, "w",
                                                            zipfile.ZIP_DEFLATED) as dst:
        for name in src.namelist():
            dst.writestr(name, buf.getvalue() if name == "policy.pth" else src.read(name))
    shutil.move(tmp_path, out)
    keep = {k: meta[k] for k in ("algo", "env_id", "env_kwargs", "residual") if k in meta}
    keep["soup"] = {"ingredients": [str(p) for p in paths],
                    "weights": list(weights) if weights is not None else None,
                    "metadata_from": str(meta_from)}
    out.with_suffix(".json").write_text(json.dumps(keep, indent=1))
    return out


Score = tuple[float, float]   # (success within 1 mm, snap rate)


def target_ratio(score: Score, success: float = 0.90, snaps: float = 0.01) -> float:
    """``max(miss / (1 - success), snap rate / snaps)`` of ``score = (success within 1 mm, snap
    rate)``: the worse of the two ratios of a result to its target (``<= 1`` iff both targets
    are met; lower is better)."""
    if not (0.0 <= success < 1.0 and snaps > 0.0):
        raise ValueError(f"targets: need 0 <= success < 1 and snaps > 0, got success={success}, "
                         f"snaps={snaps}")
    return max((1.0 - score[0]) / (1.0 - success), score[1] / snaps)


# objective name -> the sort key of a score (lower is better; a soup is kept when its key is
# not above the best so far on the key's first entry)
OBJECTIVES: dict[str, Callable[..., tuple[float, float]]] = {
    "success": lambda s, **_: (-s[0], s[1]),
    "targets": lambda s, **t: (target_ratio(s, **t), -s[0]),
}


def greedy_soup(paths: Sequence[str | Path], out: str | Path,
                score: Callable[[Path], Score], *, like: str | Path | None = None,
                log: Callable[[str], None] = print, objective: str = "success",
                targets: dict[str, float] | None = None,
                known: dict[str, Score] | None = None) -> tuple[list[Path], dict[str, Score]]:
    """Greedy soup of ``paths`` written to ``out``: ``score(model path)`` gives ``(success,
    snap rate)`` on the selection goals; ``objective`` one of :data:`OBJECTIVES` (``targets``:
    keyword arguments of :func:`target_ratio`); ``known`` scores already taken (keyed by
    ``str(path)``) are used instead of calling ``score``. Returns the kept ingredients and every
    score taken or used (keyed by ingredient path, and ``soup+<n>`` for each soup tried)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {sorted(OBJECTIVES)}, got {objective!r}")
    targets = targets or {}

    def key(sc: Score) -> tuple[float, float]:
        return OBJECTIVES[objective](sc, **targets)

    key((0.5, 0.5))    # validates the targets before any evaluation
    paths = [Path(p) for p in paths]
    like = like if like is not None else _meta_source(paths, None)
    known = known or {}
    scores: dict[str, Score] = {}
    for p in paths:
        scores[str(p)] = tuple(known[str(p)]) if str(p) in known else score(p)
        log(f"ingredient {p}: success {scores[str(p)][0]:.3f}, snaps {scores[str(p)][1]:.3f}"
            + (" (known)" if str(p) in known else ""))
    ranked = sorted(paths, key=lambda p: key(scores[str(p)]))
    kept = [ranked[0]]
    best = key(scores[str(ranked[0])])
    for p in ranked[1:]:
        trial = make_soup(kept + [p], out, like=like)
        s = score(trial)
        scores[f"soup+{len(scores)}:{p}"] = s
        ok = key(s)[0] <= best[0]
        log(f"soup + {p}: success {s[0]:.3f}, snaps {s[1]:.3f} -> {'kept' if ok else 'dropped'}")
        if ok:
            kept.append(p)
            best = key(s)
    make_soup(kept, out, like=like)
    return kept, scores


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.soup", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", help="SB3 model .zip files of one architecture")
    p.add_argument("--out", required=True, help="the soup's .zip (its .json is written beside)")
    p.add_argument("--weights", nargs="+", type=float, default=None,
                   help="one weight per model (uniform soup only; default equal)")
    p.add_argument("--like", default=None,
                   help="model whose sibling .json gives algo and env (default: the first "
                        "ingredient that has one)")
    p.add_argument("--greedy", action="store_true",
                   help="greedy soup, scored on seeded goals (--seed, --episodes, --batch)")
    p.add_argument("--seed", type=int, default=20000,
                   help="first goal seed of the greedy soup's selection goals")
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--objective", choices=sorted(OBJECTIVES), default="success",
                   help="greedy soup: what a kept ingredient must not worsen (see above)")
    p.add_argument("--target-success", type=float, default=0.90,
                   help="--objective targets: success target within 1 mm (default 0.90)")
    p.add_argument("--target-snaps", type=float, default=0.01,
                   help="--objective targets: snap-rate target (default 0.01)")
    p.add_argument("--known-scores", default=None, metavar="JSON",
                   help="greedy soup: {model path: [success, snap rate]} already taken on the "
                        "same selection goals (those ingredients are not re-scored)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        if not args.greedy:
            out = make_soup(args.models, args.out, weights=args.weights, like=args.like)
            print(f"wrote {out} ({len(args.models)} ingredients)")
            return 0
        if args.weights is not None:
            p.error("--weights applies to the uniform soup only")
        from .evaluate import load_policy, policy_env, rollout, summarize
        like = args.like or _meta_source([Path(m) for m in args.models], None)

        def score(path: Path) -> Score:
            venv, _ = policy_env(path if path.with_suffix(".json").exists() else like,
                                 args.batch)
            # an ingredient without its own .json is loaded as the model it was trained like
            policy = _load_as(path, like, venv, load_policy)
            s = summarize(rollout(policy, venv, args.episodes, seed=args.seed, progress=False))
            return s["success@1mm"], s["snap_rate"]

        known = None
        if args.known_scores is not None:
            known = json.loads(Path(args.known_scores).read_text())
            if not isinstance(known, dict) or not all(
                    isinstance(v, list) and len(v) == 2 for v in known.values()):
                raise ValueError(f"--known-scores {args.known_scores}: need a JSON object "
                                 f"{{model path: [success, snap rate]}}")
        targets = {"success": args.target_success, "snaps": args.target_snaps}
        kept, scores = greedy_soup(args.models, args.out, score, like=like,
                                   objective=args.objective, targets=targets, known=known)
    except (ValueError, KeyError, FileNotFoundError) as e:
        p.error(str(e))
    print(f"wrote {args.out}: {len(kept)} of {len(args.models)} ingredients kept")
    Path(args.out).with_suffix(".scores.json").write_text(json.dumps(scores, indent=1))
    return 0


def _load_as(path: Path, like: Path, venv, load_policy):
    """``load_policy`` of ``path``, with ``like``'s metadata when ``path`` has no ``.json``."""
    if path.with_suffix(".json").exists():
        return load_policy(str(path), venv)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d) / "model.zip"
        shutil.copy(path, tmp)
        shutil.copy(Path(like).with_suffix(".json"), tmp.with_suffix(".json"))
        return load_policy(str(tmp), venv)


if __name__ == "__main__":
    sys.exit(main())
