"""Model soups (training/soup.py, Wortsman et al. 2022): the soup's weights are the weighted
mean of its ingredients' (checked against the formula written out), the archive stays a
loadable SB3 model with the first ingredient's optimizers and entropy coefficient, the greedy
recipe keeps exactly the ingredients that do not lower the score, and mismatches are refused
by name."""

from __future__ import annotations

import json

import pytest
import torch

import envs  # noqa: F401  (registers the env ids)
from training import soup
from training.soup import average_state_dicts, greedy_soup, make_soup, target_ratio

ENV = "torchpvs/CTRReachForce-v0"


def test_the_average_is_the_weighted_mean_and_integers_are_kept():
    a = {"w": torch.tensor([1.0, 2.0]), "b": torch.tensor(4.0, dtype=torch.float32),
         "n": torch.tensor(7)}
    b = {"w": torch.tensor([3.0, -2.0]), "b": torch.tensor(0.0, dtype=torch.float32),
         "n": torch.tensor(7)}
    out = average_state_dicts([a, b], [1.0, 3.0])
    # (1 a + 3 b) / 4, by hand
    assert torch.allclose(out["w"], torch.tensor([2.5, -1.0]))
    assert out["b"].dtype == torch.float32 and float(out["b"]) == 1.0
    assert int(out["n"]) == 7 and out["n"].dtype == a["n"].dtype
    uniform = average_state_dicts([a, b])
    assert torch.allclose(uniform["w"], torch.tensor([2.0, 0.0]))


def test_mismatches_and_bad_weights_are_refused_by_name():
    a = {"layer.weight": torch.zeros(2, 3)}
    with pytest.raises(ValueError, match="layer.weight.*shape"):
        average_state_dicts([a, {"layer.weight": torch.zeros(3, 3)}])
    with pytest.raises(KeyError, match="other.weight"):
        average_state_dicts([a, {"other.weight": torch.zeros(2, 3)}])
    with pytest.raises(ValueError, match="weights"):
        average_state_dicts([a, a], [1.0, -1.0])
    with pytest.raises(ValueError, match="weights"):
        average_state_dicts([a, a], [1.0])
    with pytest.raises(ValueError, match="integer"):
        average_state_dicts([{"n": torch.tensor(1)}, {"n": torch.tensor(2)}])
    with pytest.raises(ValueError, match="at least one"):
        average_state_dicts([])


def _saved_models(tmp_path, n, arch=(8,)):
    """``n`` untrained SAC models of the force env (different seeds: different weights), each
    saved with the sibling .json that training.evaluate reads."""
    import gymnasium as gym
    from stable_baselines3 import SAC
    tmp_path.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        env = gym.make(ENV, max_episode_steps=5)
        model = SAC("MultiInputPolicy", env, seed=i, learning_starts=10, buffer_size=100,
                    policy_kwargs={"net_arch": list(arch)}, device="cpu")
        with torch.no_grad():
            model.log_ent_coef.fill_(0.1 * (i + 1))
        path = tmp_path / f"m{i}.zip"
        model.save(path)
        path.with_suffix(".json").write_text(json.dumps(
            {"algo": "sac", "env_id": ENV, "env_kwargs": {"max_episode_steps": 5}}))
        env.close()
        paths.append(path)
    return paths


def test_a_soup_is_a_loadable_model_with_the_mean_weights(tmp_path):
    from stable_baselines3 import SAC
    from stable_baselines3.common.save_util import load_from_zip_file
    paths = _saved_models(tmp_path, 3)
    out = make_soup(paths, tmp_path / "soup" / "s.zip", weights=[1.0, 1.0, 2.0])
    params = [load_from_zip_file(p, device="cpu")[1]["policy"] for p in paths]
    _, sp, svars = load_from_zip_file(out, device="cpu")
    for k, v in sp["policy"].items():
        want = (params[0][k] + params[1][k] + 2 * params[2][k]) / 4
        assert torch.allclose(v, want, atol=1e-7), k
    # the entropy coefficient is the first ingredient's, not an average
    assert float(svars["log_ent_coef"].detach()) == pytest.approx(0.1)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["algo"] == "sac" and meta["env_id"] == ENV
    assert meta["soup"]["ingredients"] == [str(p) for p in paths]
    model = SAC.load(out, device="cpu")   # a real SB3 archive
    obs = model.observation_space.sample()
    act, _ = model.predict(obs, deterministic=True)
    assert model.action_space.contains(act)


def test_a_soup_of_one_model_acts_as_that_model(tmp_path):
    from stable_baselines3 import SAC
    (path,) = _saved_models(tmp_path, 1)
    out = make_soup([path, path], tmp_path / "twice.zip")
    a, b = SAC.load(path, device="cpu"), SAC.load(out, device="cpu")
    a.observation_space.seed(3)
    for _ in range(5):
        obs = a.observation_space.sample()
        act_a, act_b = (m.predict(obs, deterministic=True)[0] for m in (a, b))
        assert (act_a == act_b).all()


def test_other_architectures_cannot_be_souped(tmp_path):
    small = _saved_models(tmp_path / "a", 1, arch=(8,))
    wide = _saved_models(tmp_path / "b", 1, arch=(12,))
    with pytest.raises(ValueError, match="shape"):
        make_soup(small + wide, tmp_path / "x.zip")


def test_the_greedy_recipe_keeps_what_does_not_lower_the_score(tmp_path):
    paths = _saved_models(tmp_path, 4)
    alone = {paths[0]: 0.80, paths[1]: 0.90, paths[2]: 0.85, paths[3]: 0.70}
    # a soup scores by which ingredients it holds: adding m0 lowers it, m2 and m3 raise it
    effect = {"m1.zip": 0.0, "m2.zip": 0.01, "m0.zip": -0.05, "m3.zip": 0.02}

    def score(path):
        if path in alone:
            return alone[path], 0.0
        held = json.loads(path.with_suffix(".json").read_text())["soup"]["ingredients"]
        return 0.90 + sum(effect[p.rsplit("/", 1)[-1]] for p in held), 0.0

    kept, scores = greedy_soup(paths, tmp_path / "greedy.zip", score, log=lambda _: None)
    # ranked 0.90 (m1), 0.85 (m2), 0.80 (m0), 0.70 (m3): m2 kept, m0 dropped, m3 kept
    assert kept == [paths[1], paths[2], paths[3]]
    final = json.loads((tmp_path / "greedy.json").read_text())["soup"]["ingredients"]
    assert final == [str(p) for p in kept]
    assert len(scores) == 4 + 3


def test_the_target_ratio_is_the_worse_of_the_two_ratios_to_target():
    # by hand: miss 0.10 / 0.10 = 1.0 and snaps 0.02 / 0.01 = 2.0 -> 2.0
    assert target_ratio((0.90, 0.02)) == pytest.approx(2.0)
    # miss 0.15 / 0.10 = 1.5 beats snaps 0.005 / 0.01 = 0.5 -> 1.5
    assert target_ratio((0.85, 0.005)) == pytest.approx(1.5)
    # both met iff <= 1
    assert target_ratio((0.91, 0.008)) <= 1.0 < target_ratio((0.91, 0.012))
    assert target_ratio((0.7, 0.1), success=0.5, snaps=0.2) == pytest.approx(0.6)
    with pytest.raises(ValueError, match="targets"):
        target_ratio((0.9, 0.0), success=1.0)
    with pytest.raises(ValueError, match="targets"):
        target_ratio((0.9, 0.0), snaps=0.0)


def test_the_greedy_recipe_under_the_targets_objective_and_known_scores(tmp_path):
    """Under ``targets`` an ingredient that raises success but also snaps is dropped when the
    snaps are the binding target; known scores are used without calling the scorer."""
    paths = _saved_models(tmp_path, 3)
    alone = {paths[0]: (0.90, 0.020), paths[1]: (0.85, 0.004), paths[2]: (0.88, 0.012)}
    # ranked by T alone (max(miss / 0.10, snaps / 0.01)): m2 1.2, m1 1.5, m0 2.0.
    # m2 + m1 -> (0.89, 0.008): T 1.1 <= 1.2, kept; + m0 -> (0.91, 0.016): T 1.6, dropped
    # although it raises success (the success objective would keep it)
    soups = {("m1.zip", "m2.zip"): (0.89, 0.008), ("m0.zip", "m1.zip", "m2.zip"): (0.91, 0.016)}
    calls = []

    def score(path):
        calls.append(path)
        held = json.loads(path.with_suffix(".json").read_text())
        if "soup" not in held:
            return alone[path]
        return soups[tuple(sorted(p.rsplit("/", 1)[-1] for p in held["soup"]["ingredients"]))]

    known = {str(paths[0]): list(alone[paths[0]])}
    kept, scores = greedy_soup(paths, tmp_path / "t.zip", score, objective="targets",
                               known=known, log=lambda _: None)
    assert kept == [paths[2], paths[1]]
    assert paths[0] not in calls and scores[str(paths[0])] == (0.90, 0.020)   # known, not re-run
    assert len(calls) == 2 + 2                       # m1, m2 alone; two soups
    with pytest.raises(ValueError, match="objective"):
        greedy_soup(paths, tmp_path / "x.zip", score, objective="speed", log=lambda _: None)


def test_the_cli_writes_a_soup_and_refuses_missing_metadata(tmp_path, capsys):
    paths = _saved_models(tmp_path, 2)
    assert soup.main(["--out", str(tmp_path / "u.zip"), *map(str, paths)]) == 0
    assert (tmp_path / "u.zip").exists() and (tmp_path / "u.json").exists()
    for p in paths:
        p.with_suffix(".json").unlink()
    with pytest.raises(SystemExit):
        soup.main(["--out", str(tmp_path / "v.zip"), *map(str, paths)])
    assert "--like" in capsys.readouterr().err


def test_the_greedy_cli_scores_on_seeded_goals_and_writes_its_scores(tmp_path):
    """The CLI's greedy path end to end (two untrained ingredients, one short evaluation
    each): the soup, its .json and the scores file are written, every score is a rate."""
    paths = _saved_models(tmp_path, 2)
    out = tmp_path / "g.zip"
    assert soup.main(["--out", str(out), "--greedy", "--episodes", "1", "--batch", "1",
                      *map(str, paths)]) == 0
    scores = json.loads(out.with_suffix(".scores.json").read_text())
    assert len(scores) == 3
    assert all(0.0 <= s <= 1.0 and 0.0 <= snaps <= 1.0 for s, snaps in scores.values())
    held = json.loads(out.with_suffix(".json").read_text())["soup"]["ingredients"]
    assert 1 <= len(held) <= 2 and set(held) <= {str(p) for p in paths}


def test_the_greedy_cli_takes_the_targets_objective_and_known_scores(tmp_path, capsys):
    paths = _saved_models(tmp_path, 2)
    known = tmp_path / "known.json"
    known.write_text(json.dumps({str(paths[0]): [0.5, 0.25]}))
    out = tmp_path / "k.zip"
    assert soup.main(["--out", str(out), "--greedy", "--episodes", "1", "--batch", "1",
                      "--objective", "targets", "--known-scores", str(known),
                      *map(str, paths)]) == 0
    scores = json.loads(out.with_suffix(".scores.json").read_text())
    assert scores[str(paths[0])] == [0.5, 0.25]
    assert "(known)" in capsys.readouterr().out
    known.write_text(json.dumps({str(paths[0]): 0.5}))
    with pytest.raises(SystemExit):
        soup.main(["--out", str(out), "--greedy", "--known-scores", str(known), *map(str, paths)])
    assert "--known-scores" in capsys.readouterr().err
