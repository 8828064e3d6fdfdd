"""Bad input anywhere (issue 22): a table of bad inputs across the commands, the Python API
and both adapters, each refused the documented way.

* a command: exit code 2, at most two lines on stderr (``error: ...``), no traceback, and
  no file created, changed or removed in the working directory (a refused command writes
  nothing: no run folder, no ``.hydra/``, no result);
* the Python API and the adapters: the documented exception type (``ValueError``, of which
  :class:`~fleet_torchrl.utils.checks.ConfigError` is one) with a one-line message.

Most cases run in this process (the commands' entry points under ``sys.argv``, as the
console scripts call them); a few go through a real subprocess to check what a user sees.
"""

from __future__ import annotations

import io
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fleet_torchrl.env import MDPConfig
from fleet_torchrl.sim import SiteConfig
from fleet_torchrl.utils.checks import ConfigError


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder under ``root``: (size, mtime in ns) by relative path."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = (st.st_size if p.is_file() else -1, st.st_mtime_ns)
    return out


def _result(n: int = 3, trips=None) -> dict:
    trips = [10, 11, 12][:n] if trips is None else trips
    return {"policy": "x", "seed": 0, "n_sims": n, "ticks": 100,
            "records": {"trips": trips, "queue": [0] * n, "failed": [False] * n,
                        "ticks_survived": [100] * n}}


@pytest.fixture
def workdir(tmp_path, monkeypatch, saved_policies):
    """A working directory holding what the cases refer to: a file, a folder named like a
    file, results good and bad, saved policies, a folder of runs that are no grid."""
    w = tmp_path / "work"
    w.mkdir()
    (w / "afile").write_text("not a folder\n")
    (w / "taken.json").mkdir()
    good = _result()
    bad = {"number": 42, "null": None, "list": [1, 2], "empty": {**_result(), "records": {}},
           "lengths": {**_result(), "records": {**_result()["records"], "trips": [1, 2]}},
           "nan_trips": _result(trips=[1, None, 3]), "negative": _result(trips=[1, -5, 3]),
           "zero_sims": {**_result(), "n_sims": 0}, "missing": {"policy": "x"},
           "zero_base": _result(trips=[0, 0, 0])}
    (w / "good.json").write_text(json.dumps(good))
    for name, value in bad.items():
        (w / f"{name}.json").write_text(json.dumps(value))
    (w / "nan.json").write_text(json.dumps(_result()).replace("11", "NaN"))
    (w / "garbage.json").write_text("{not json")
    # a folder of runs that are not a grid's (a single train run, an evaluation)
    for name, job in (("0", "train"), ("1", "evaluate")):
        (w / "runs" / name / ".hydra").mkdir(parents=True)
        (w / "runs" / name / ".hydra" / "hydra.yaml").write_text(
            f"hydra:\n  mode: RUN\n  job:\n    name: {job}\n")
        (w / "runs" / name / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
        (w / "runs" / name / "train_summary.json").write_text('{"best": {"trips": 1}}')
    # a sweep folder of another parameter (a p_c point must not be filed with N_V points)
    (w / "sweeps" / "mine").mkdir(parents=True)
    (w / "sweeps" / "mine" / "p_c=0.5.json").write_text('{"rows": []}')
    monkeypatch.chdir(w)
    return w


P = "{w}"  # the working directory, filled in per case
# (command module, arguments, a piece of the one-line message)
COMMANDS = [
    # the site, the MDP, the agent, seeds (the Python API's checks, through Hydra)
    ("evaluate", ["site.p_c=5.0"], "site.p_c"),
    ("evaluate", ["site.soc_low=-50"], "site.soc_low"),
    ("evaluate", ["site.e_move=-3"], "site.e_move"),
    ("evaluate", ["site.t_c=-5"], "site.t_c"),
    ("evaluate", ["site.n_vehicles=0"], "site.n_vehicles"),
    ("evaluate", ["site.n_vehicles=2.5"], "site.n_vehicles"),
    ("evaluate", ["site.p_c=nan"], "site.p_c"),
    ("evaluate", ["site.p_c=abc"], "site.p_c"),
    ("evaluate", ["site=nonexistent"], "site"),
    ("evaluate", ["+site.pc=0.5"], "site.pc"),
    ("evaluate", ["site.ranges.t_c=[20,40]"], "site=randomized"),
    ("evaluate", ["site.ranges.p_c=[0.1,0.2]"], "site=randomized"),
    ("evaluate", ["mdp.gamma=5"], "mdp.gamma"),
    ("evaluate", ["mdp.tau_e=0"], "mdp.tau_e"),
    ("evaluate", ["mdp.p_f=-1"], "mdp.p_f"),
    ("evaluate", ["mdp.reward=bogus"], "mdp.reward"),
    ("evaluate", ["seed=-1"], "seed"),
    ("evaluate", ["eval.seed=-1"], "eval.seed"),
    ("evaluate", ["eval.seed=18446744073709551616"], "eval.seed"),
    ("evaluate", ["eval.n_sims=0"], "eval.n_sims"),
    ("evaluate", ["eval.n_sims=-3"], "eval.n_sims"),
    ("evaluate", ["eval.n_sims=100000000"], "eval.n_sims"),
    ("evaluate", ["eval.ticks=0"], "eval.ticks"),
    ("evaluate", ["eval.device=foo"], "eval.device"),
    ("evaluate", ["agent=nonexistent"], "agent"),
    ("evaluate", ["agent.threshold=150"], "agent.threshold"),
    ("evaluate", ["state=bogus"], "state"),
    # output paths, before any simulation and before the run folder
    ("evaluate", ["eval.out=taken.json"], "eval.out"),
    ("evaluate", ["eval.out=result.txt"], "eval.out"),
    ("evaluate", ["eval.out=/proc/x.json"], "eval.out"),
    ("evaluate", ["eval.out=afile/r.json"], "eval.out"),
    ("evaluate", ["hydra.run.dir=afile"], "hydra.run.dir"),
    ("evaluate", ["hydra.run.dir=afile/run"], "hydra.run.dir"),
    ("evaluate", ["hydra.run.dir=/proc/run"], "hydra.run.dir"),
    ("evaluate", ["agent=dqn", "agent.policy=missing/policy.pt"], "missing"),
    ("evaluate", ["agent=dqn", "agent.policy=afile"], "afile"),
    ("evaluate", ["agent=dqn", "agent.policy=good.json"], "good.json"),
    ("evaluate", ["agent=dqn", "table.policies_dir=nowhere"], "nowhere"),
    # training: sizes that would not fit, a diverging objective, outputs, resume
    ("train", ["agent=dqn", "network.width=65536", "network.depth=64"], "network"),
    ("train", ["agent=dqn", "network.buffer_size=100000000000"], "network.buffer_size"),
    ("train", ["agent=dqn", "network.batch_size=0"], "network.batch_size"),
    ("train", ["agent=dqn", "network.width=0"], "network.width"),
    ("train", ["agent=dqn", "network.lr=-1"], "network.lr"),
    ("train", ["agent=dqn", "agent.num_sites=0"], "agent.num_sites"),
    ("train", ["agent=dqn", "mdp.p_f=1e300"], "mdp.p_f"),
    ("train", ["agent=dqn", "mdp.p_q=inf"], "mdp.p_q"),
    ("train", ["agent=dqn", "train.max_episodes=0"], "train.max_episodes"),
    ("train", ["agent=dqn", "train.out_dir=afile"], "train.out_dir"),
    ("train", ["agent=dqn", "train.out_dir=/proc/x"], "train.out_dir"),
    ("train", ["agent=dqn", "table.policies_dir=afile"], "table.policies_dir"),
    ("train", ["agent=dqn", "resume=true", "hydra.run.dir=fresh"], "no checkpoint"),
    ("train", ["agent=rule"], "agent=rule"),
    ("train", ["agent=search", "agent.population=100000000000"], "agent"),
    ("train", ["agent=tabular", "agent.alpha=5"], "agent.alpha"),
    ("train", ["agent=dqn", "train.device=cuda:99"], "train.device"),
    ("train", ["agent=dqn", "agent.policy=results/policies/dqn_partial"], "agent.policy"),
    # compare: results that are no results, and a gain that would be +nan %
    ("compare", ["result=number.json", "baseline=good.json"], "number.json"),
    ("compare", ["result=null.json", "baseline=good.json"], "null.json"),
    ("compare", ["result=list.json", "baseline=good.json"], "list.json"),
    ("compare", ["result=empty.json", "baseline=good.json"], "empty.json"),
    ("compare", ["result=lengths.json", "baseline=good.json"], "lengths.json"),
    ("compare", ["result=nan_trips.json", "baseline=good.json"], "nan_trips.json"),
    ("compare", ["result=nan.json", "baseline=good.json"], "nan.json"),
    ("compare", ["result=negative.json", "baseline=good.json"], "negative.json"),
    ("compare", ["result=zero_sims.json", "baseline=good.json"], "zero_sims.json"),
    ("compare", ["result=missing.json", "baseline=good.json"], "missing.json"),
    ("compare", ["result=garbage.json", "baseline=good.json"], "garbage.json"),
    ("compare", ["result=good.json", "baseline=zero_base.json"], "trips"),
    ("compare", ["result=good.json", "baseline=nowhere.json"], "nowhere.json"),
    ("compare", ["result=good.json"], "baseline"),
    ("compare", ["result=good.json", "baseline=taken.json"], "taken.json"),
    ("compare", ["result=good.json", "baseline=good.json", "bogus=1"], "bogus"),
    # report, grid, the sweeps' summary
    ("report", ["results=.", "out=/proc/report.md"], "out"),
    ("report", ["results=.", "out=taken.json"], "out"),
    ("report", ["results=nowhere"], "results"),
    ("report", ["results=afile"], "results"),
    ("report", ["results=."], "table"),
    ("grid", ["sweep_dir=runs"], "no grid runs"),
    ("grid", ["sweep_dir=nowhere"], "sweep_dir"),
    ("grid", ["sweep_dir=afile"], "sweep_dir"),
    ("grid", ["sweep_dir=runs", "out=afile"], "out"),
    ("sweeps_summary", ["name=nothing"], "nothing"),
    ("sweeps_summary", ["out=afile"], "out"),
    # bench: every bad setting, before anything is measured
    ("bench", ["bench.batches=[0]"], "bench.batches"),
    ("bench", ["bench.batches=[-1]"], "bench.batches"),
    ("bench", ["bench.batches=[]"], "bench.batches"),
    ("bench", ["bench.repeats=0"], "bench.repeats"),
    ("bench", ["bench.site_ticks=nan"], "bench.site_ticks"),
    ("bench", ["bench.site_ticks=0"], "bench.site_ticks"),
    ("bench", ["bench.env_steps=0"], "bench.env_steps"),
    ("bench", ["bench.device=foo"], "bench.device"),
    ("bench", ["bench.device=cuda:99"], "bench.device"),
    ("bench", ["bench.batches=[1000000000]"], "bench.batches"),
    ("bench", ["bench.out=/proc/b.json"], "bench.out"),
    ("bench", ["bench.out=taken.json"], "bench.out"),
    ("bench", ["bench.out=afile/b.json"], "bench.out"),
    # the experiments: sweeps, table, objective, maps
    ("sweeps", ["sweep.param=n_vehicles", "sweep.value=2.7"], "sweep.value"),
    ("sweeps", ["sweep.param=n_vehicles", "sweep.value=0"], "sweep.value"),
    ("sweeps", ["sweep.param=t_c", "sweep.value=-5"], "sweep.value"),
    ("sweeps", ["sweep.param=p_c", "sweep.value=1.5"], "sweep.value"),
    ("sweeps", ["sweep.param=bogus"], "sweep.param"),
    ("sweeps", ["sweep.param=n_vehicles", "sweep.value=3", "sweep.name=mine",
                "sweep.out=sweeps"], "sweep.name"),
    ("sweeps", ["sweep.out=afile"], "sweep.out"),
    # a generalist's recipe (site=randomized) cannot train on a point's own site
    ("sweeps", ["sweep.distil=generalist"], "sweep.distil"),
    ("sweeps", ["+sweep.specialists.specialist_g=generalist_dqn"],
     "sweep.specialists.specialist_g"),
    ("table", ["table.policies_dir=afile"], "table.policies_dir"),
    ("table", ["table.seeds=0"], "table.seeds"),
    ("table", ["table.only=[nonexistent]"], "nonexistent"),
    ("table", ["table.out=afile"], "table.out"),
    ("objective", ["table.policies_dir=nowhere"], "table.policies_dir"),
    ("objective", ["objective.n_sites=0"], "objective.n_sites"),
    ("objective", ["objective.out=afile"], "objective.out"),
    ("policy_maps", ["maps.out=afile"], "maps.out"),
]


@pytest.mark.parametrize("module,args,msg", COMMANDS,
                         ids=[f"{m}:{' '.join(a)}" for m, a, _ in COMMANDS])
def test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        module, args, msg, workdir, command, capsys):
    import importlib

    main = importlib.import_module(f"fleet_torchrl.{module}").main
    before = snapshot(workdir)
    capsys.readouterr()
    code = command(main, *args)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert 1 <= len(lines) <= 2 and "Traceback" not in err, err
    assert lines[-1].startswith("error: ") and msg in lines[-1], err
    assert snapshot(workdir) == before, "a refused command changed files"


# ------------------------------------------------------------------ the Python API
def _env(**kw):
    from fleet_torchrl.env import FleetChargingEnv

    return FleetChargingEnv(**kw)


def _gym(**kw):
    from fleet_torchrl.env.gym import FleetGymEnv

    return FleetGymEnv(**kw)


def _vec(**kw):
    from fleet_torchrl.env.gym import FleetVecEnv

    return FleetVecEnv(**kw)


BAD_ACTIONS = [2, -1, 7, 0.2, 0.7, float("nan"), float("inf"), "charge", None, [0, 1],
               np.array([0.5]), torch.tensor([3]), torch.tensor([[1, 0]]), object()]

API = [
    ("SiteConfig(p_c=5.0)", lambda: SiteConfig(p_c=5.0)),
    ("SiteConfig(soc_low=-50)", lambda: SiteConfig(soc_low=-50)),
    ("SiteConfig(e_move=-3)", lambda: SiteConfig(e_move=-3)),
    ("SiteConfig(t_c=-5)", lambda: SiteConfig(t_c=-5)),
    ("SiteConfig(n_vehicles=0)", lambda: SiteConfig(n_vehicles=0)),
    ("SiteConfig(n_vehicles=2.5)", lambda: SiteConfig(n_vehicles=2.5)),
    ("SiteConfig(p_c=nan)", lambda: SiteConfig(p_c=float("nan"))),
    ("SiteConfig(p_c='x')", lambda: SiteConfig(p_c="x")),
    ("MDPConfig(gamma=5)", lambda: MDPConfig(gamma=5)),
    ("MDPConfig(tau_e=0)", lambda: MDPConfig(tau_e=0)),
    ("MDPConfig(p_f=1e300)", lambda: MDPConfig(p_f=1e300)),
    ("MDPConfig(reward=bogus)", lambda: MDPConfig(reward="bogus")),
    ("env num_sites=0", lambda: _env(num_sites=0)),
    ("env num_sites=-1", lambda: _env(num_sites=-1)),
    ("env num_sites=2.5", lambda: _env(num_sites=2.5)),
    ("env num_sites=True", lambda: _env(num_sites=True)),
    ("env num_sites=10**12", lambda: _env(num_sites=10**12)),
    ("env seed=-1", lambda: _env(seed=-1)),
    ("env seed=2**64", lambda: _env(seed=2**64)),
    ("env seed=1.5", lambda: _env(seed=1.5)),
    ("env site=n_vehicles 0 dict", lambda: _env(site={"n_vehicles": 0})),
    ("env site=unknown key", lambda: _env(site={"pc": 0.5})),
    ("env encoding=bogus", lambda: _env(encoding="bogus")),
    ("env set_seed(-1)", lambda: _env().set_seed(-1)),
    ("gym seed=-1", lambda: _gym(seed=-1)),
    ("gym reset(seed=2**64)", lambda: _gym().reset(seed=2**64)),
    ("gym site=dict p_c 5", lambda: _gym(site={"p_c": 5.0})),
    ("gym site=unknown key", lambda: _gym(site={"bogus": 1})),
    ("gym mdp=dict gamma 5", lambda: _gym(mdp={"gamma": 5})),
    ("vec num_sites=0", lambda: _vec(num_sites=0)),
    ("vec seed=-1", lambda: _vec(seed=-1)),
]


@pytest.mark.parametrize("make", [m for _, m in API], ids=[n for n, _ in API])
def test_the_python_api_refuses_bad_input_with_a_value_error(make):
    with pytest.raises(ValueError) as e:
        make()
    assert "\n" not in str(e.value) and str(e.value)


def _step_env(action):
    env = _env(num_sites=2)
    td = env.reset()
    if action is not None:  # None: no action at all
        td._tensordict["action"] = action  # past TensorDict's own shape check: the env's
    env.step(td)


def _step_gym(action):
    env = _gym()
    env.reset(seed=1)
    env.step(action)


def _step_vec(action):
    env = _vec(num_sites=1)
    env.reset()
    env.step_async(action)


@pytest.mark.parametrize("action", BAD_ACTIONS, ids=[repr(a)[:20] for a in BAD_ACTIONS])
@pytest.mark.parametrize("adapter", ["gym", "vec"])
def test_both_adapters_refuse_the_same_bad_actions(adapter, action):
    """One rule (``check_actions``) in the Gymnasium and the Stable-Baselines3 adapter: an
    action is 0 or 1, one per site; 0.7, NaN, 2, -1, a string, a missing action are refused
    in both (never rounded, never read as "charge")."""
    step = {"gym": _step_gym, "vec": _step_vec}[adapter]
    with pytest.raises(ValueError) as e:
        step(action)
    assert "\n" not in str(e.value)


ENV_ACTIONS = [torch.tensor([2, 0]), torch.tensor([-1, 0]), torch.tensor([0.7, 1.0]),
               torch.tensor([float("nan"), 0.0]), torch.tensor([1]), torch.tensor([0, 1, 1]),
               torch.tensor([[1, 0, 1, 0]]), torch.tensor(1), None]


@pytest.mark.parametrize("action", ENV_ACTIONS, ids=[repr(a) for a in ENV_ACTIONS])
def test_the_env_refuses_the_same_bad_actions(action):
    with pytest.raises(ValueError) as e:
        _step_env(action)
    assert "\n" not in str(e.value)


def test_good_actions_pass_in_all_three_alike():
    """What the rule allows: 0 and 1 as ints, bools, or floats exactly 0.0 / 1.0."""
    from fleet_torchrl.env.fleet_env import check_actions

    for a in (1, True, 1.0, np.int64(1), np.array([1]), torch.tensor(1.0), [1]):
        assert check_actions(a, 1).tolist() == [1]
    assert check_actions(torch.tensor([[0], [1]]), 2).tolist() == [0, 1]
    g = _gym()
    g.reset(seed=3)
    g.step(np.int64(1))
    v = _vec(num_sites=2)
    v.reset()
    v.step(np.array([0, 1]))


# ------------------------------------------------------------------ files
def test_policy_files_refuse_corruption_and_non_finite_weights(tmp_path, saved_policies):
    """A flipped byte in the weights, a hash that does not match, NaN weights: refused at
    load (``ValueError``, one line); NaN weights are refused at save too (nothing
    written)."""
    from fleet_torchrl.agents import load_policy_file, save_policy
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.policy_files import HASH_KEY, NonFiniteWeights

    src = saved_policies / "dqn_partial" / "policy.pt"
    bundle = torch.load(src, weights_only=True)
    cases = {}
    flipped = {**bundle, "state_dict": {k: v.clone() for k, v in bundle["state_dict"].items()}}
    key = next(k for k, v in flipped["state_dict"].items() if v.is_floating_point())
    flipped["state_dict"][key].view(-1).view(torch.uint8)[0] ^= 0x01
    cases["flipped"] = flipped
    cases["wrong_hash"] = {**bundle, HASH_KEY: "0" * 64}
    nan = {**bundle, "state_dict": {k: v.clone() for k, v in bundle["state_dict"].items()}}
    nan["state_dict"][key].fill_(float("nan"))
    cases["nan_unhashed"] = {k: v for k, v in nan.items() if k != HASH_KEY}
    cases["no_tensors"] = {**bundle, "state_dict": {"w": [1, 2]}}
    cases["not_a_dict"] = [1, 2, 3]
    for name, value in cases.items():
        buf = io.BytesIO()
        torch.save(value, buf)
        (tmp_path / f"{name}.pt").write_bytes(buf.getvalue())
        with pytest.raises(ValueError) as e:
            load_policy_file(tmp_path / f"{name}.pt")
        assert "\n" not in str(e.value), name
    raw = bytearray(src.read_bytes())  # a byte flipped in the file itself
    raw[len(raw) // 2] ^= 0xFF
    (tmp_path / "raw.pt").write_bytes(bytes(raw))
    with pytest.raises(ValueError):
        load_policy_file(tmp_path / "raw.pt")
    pol = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial")
    with torch.no_grad():
        next(pol.parameters()).fill_(float("inf"))
    with pytest.raises(NonFiniteWeights):
        save_policy(tmp_path / "inf" / "policy.pt", pol, "dqn")
    assert not (tmp_path / "inf" / "policy.pt").exists()


def test_result_files_that_are_no_results_are_refused(tmp_path):
    from fleet_torchrl.evaluation.results import compare, load_result

    (tmp_path / "good.json").write_text(json.dumps(_result()))
    for name, value in {"number": 3, "null": None, "str": "x", "no_records": {
            **_result(), "records": None}, "trips_str": _result(trips=["a", "b", "c"]),
            "inf": {**_result(), "records": {**_result()["records"], "queue": [0, 0, 1e999]}},
            "bool_sims": {**_result(), "n_sims": True}}.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(value))
        with pytest.raises(ValueError):
            load_result(tmp_path / f"{name}.json")
        with pytest.raises(ValueError):
            compare(tmp_path / f"{name}.json", tmp_path / "good.json")
    g = compare(tmp_path / "good.json", tmp_path / "good.json")
    assert math.isfinite(g["gain_pct"])


@pytest.mark.parametrize("setting,path,kind", [
    ("x.out", "/proc/x", "file"), ("x.out", "/sys/x", "dir"), ("x.out", "", "file"),
    ("x.out", "afile", "dir"), ("x.out", "taken.json", "file"), ("x.out", "afile/x", "file")])
def test_output_paths_are_checked_before_the_work(setting, path, kind, workdir):
    from fleet_torchrl.utils.paths import check_output

    with pytest.raises(ConfigError, match=setting.replace(".", r"\.")):
        check_output(setting, path, kind)


# ------------------------------------------------------------------ real command lines
CLI = [
    (["fleet_torchrl.evaluate", "site.p_c=5"], "site.p_c"),
    (["fleet_torchrl.train", "agent=dqn", "mdp.p_f=1e300"], "mdp.p_f"),
    (["fleet_torchrl.compare", "result=number.json", "baseline=good.json"], "number.json"),
    (["fleet_torchrl.bench", "bench.repeats=0"], "bench.repeats"),
    (["fleet_torchrl.grid", "sweep_dir=runs"], "no grid runs"),
]


@pytest.mark.parametrize("argv,msg", CLI, ids=[" ".join(a) for a, _ in CLI])
def test_real_command_lines_say_one_line_and_exit_2(argv, msg, workdir):
    before = snapshot(workdir)
    r = subprocess.run([sys.executable, "-m", *argv], cwd=workdir, capture_output=True,
                       text=True, timeout=120)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and 1 <= len(lines) <= 2, r.stderr
    assert "Traceback" not in r.stderr and msg in lines[-1], r.stderr
    assert snapshot(workdir) == before


# ------------------------------------------------------------------ nothing clobbered
TINY = ["agent=tabular", "agent.num_sites=16", "train.max_episodes=32", "train.eval_every=1",
        "train.eval_sims=8", "train.eval_ticks=300", "train.checkpoint_every=1",
        "train.progress=false", "mdp.tau_e=300", "train.tensorboard=false"]


def test_a_refused_resume_writes_nothing(tmp_path, monkeypatch, command, capsys):
    """A resume with other settings is refused before Hydra writes the run's ``.hydra/``
    and before the run's ``run_info.json`` is rewritten: the run folder stays as it was."""
    from fleet_torchrl import train

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    common = [*TINY, f"train.out_dir={tmp_path / 'policy'}", f"hydra.run.dir={run}"]
    assert command(train.main, *common) == 0
    assert (run / "checkpoint.ckpt").is_file() and (run / "run_info.json").is_file()
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert command(train.main, *common, "mdp.reward=throughput", "resume=true") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another configuration" in err[0], err
    assert snapshot(tmp_path) == before


def test_a_diverged_training_publishes_nothing(tmp_path):
    """A policy whose weights turn NaN (an overflowing reward, a learning rate too large) stops
    the training at its next evaluation with one line; no policy is published."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.training import Trainer

    cfg = compose_config([*TINY, f"train.out_dir={tmp_path / 'policy'}"])
    tr = Trainer(cfg, tmp_path / "run")
    tr.learner.table.q.fill_(float("nan"))
    with pytest.raises(ValueError, match="diverged") as e:
        tr.run()
    assert "\n" not in str(e.value) and "nothing is published" in str(e.value)
    assert not (tmp_path / "policy" / "policy.pt").exists()


def test_gymnasium_make_checks_a_site_given_as_a_dict():
    gymnasium = pytest.importorskip("gymnasium")
    from fleet_torchrl.env.gym import GYM_ID, register_envs

    register_envs()
    env = gymnasium.make(GYM_ID, site={"p_c": 0.6})
    assert env.unwrapped.env.site_cfg.p_c == 0.6
    for bad in ({"p_c": 5.0}, {"n_vehicles": 0}, {"bogus": 1}, {"ranges": {"x": [1, 2]}}):
        with pytest.raises(ValueError) as e:
            gymnasium.make(GYM_ID, site=bad)
        assert "\n" not in str(e.value)


def test_files_are_written_with_the_users_umask(tmp_path):
    """Results and policies are for a team to read: the umask decides, not mkstemp's 0600."""
    from fleet_torchrl.utils.runinfo import write_json

    old = os.umask(0o022)
    try:
        write_json(tmp_path / "r.json", {"a": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "r.json").stat().st_mode & 0o777 == 0o644


def test_a_budget_that_is_not_what_runs_is_announced(tmp_path, caplog):
    """train.max_episodes=1 trains a whole round of agent.num_sites episodes: said in one
    warning line, not silently."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.training import Trainer

    cfg = compose_config([*TINY, "train.max_episodes=1", f"train.out_dir={tmp_path / 'p'}"])
    with caplog.at_level("WARNING"):
        Trainer(cfg, tmp_path / "run")
    said = [r.getMessage() for r in caplog.records if "train.max_episodes=1" in r.getMessage()]
    assert len(said) == 1 and "16 episodes" in said[0] and "\n" not in said[0], said


def test_a_second_process_cannot_train_in_a_held_run_folder(tmp_path):
    """A run folder is held by the process that trains in it: a second process (e.g. a
    training left running by a killed ``make table`` beside the one that resumes it) stops
    with one line naming the holder, before it writes anything; the hold ends with its
    process however it ends, and the same process may hold the folder again."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.training import Trainer
    from fleet_torchrl.utils.checks import SetupError
    from fleet_torchrl.utils.paths import hold_run_dir, release_run_dir

    code = ("import sys, time; from fleet_torchrl.utils.paths import hold_run_dir; "
            "hold_run_dir(sys.argv[1]); print('held', flush=True); time.sleep(600)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(SetupError, match=f"in use by process {holder.pid}:") as e:
            hold_run_dir(tmp_path)
        assert "\n" not in str(e.value)
        before = snapshot(tmp_path)
        cfg = compose_config([*TINY, f"train.out_dir={tmp_path / 'policy'}"])
        with pytest.raises(SetupError, match="a run already trains there"):
            Trainer(cfg, tmp_path)
        assert snapshot(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()
    hold_run_dir(tmp_path)  # killed, the holder let go
    hold_run_dir(tmp_path)  # and this process may hold it again
    release_run_dir(tmp_path)


def test_an_exception_is_told_in_one_short_line():
    """What the kernel's setup errors and an unreadable policy file quote of the exception."""
    from fleet_torchrl.utils.checks import exception_line

    assert exception_line(OSError("disk full\nsecond line")) == "OSError: disk full"
    assert exception_line(RuntimeError("x" * 500)) == "RuntimeError: " + "x" * 200
    assert exception_line(KeyError()) == "KeyError"
    assert exception_line(ValueError("  \n ")) == "ValueError"


# ---- one line for every failure: composition, environment, devices, numbers, the env
def _no_device(kind: str) -> bool:
    if kind == "cuda":
        return not torch.cuda.is_available()
    mps = getattr(torch.backends, "mps", None)
    return mps is None or not mps.is_available()


# a site whose initial states keep failing before their first decision: one vehicle on 61
# candidate nodes, a move costs everything it has (it fails unless it starts at D)
NEVER_STARTS = ["site.n_nodes=62", "site.n_vehicles=1", "site.closed_node=20", "site.e_move=100"]
ONE_LINE_COMMANDS = [
    ("evaluate", ["eval.n_sims=${oc.env:FLEET_TORCHRL_UNSET_VAR}"], "FLEET_TORCHRL_UNSET_VAR"),
    ("evaluate", ["~agent"], "agent=rule"),
    ("evaluate", ["=0.5"], "=0.5"),
    ("evaluate", ["site=null"], "site=null"),
    ("evaluate", ["~agent=1"], "~agent=1"),
    ("train", ["agent=dqn", "train.max_episodes=1000000000000000000"], "train.max_episodes"),
    ("train", ["agent=dqn", "train.max_episodes=1e18"], "train.max_episodes"),
    ("train", ["agent=dqn", "agent.steps_per_round=10000000000"], "agent.steps_per_round"),
    ("train", ["agent=tabular", "agent.num_sites=64", "train.max_episodes=64",
               *NEVER_STARTS], "site.xi"),
    *([("evaluate", ["eval.device=mps"], "eval.device")] if _no_device("mps") else []),
    *([("evaluate", ["eval.device=cuda"], "eval.device"),
       ("train", ["agent=dqn", "train.device=cuda"], "train.device")]
      if _no_device("cuda") else []),
]


@pytest.mark.parametrize("module,args,msg", ONE_LINE_COMMANDS,
                         ids=[f"{m}:{' '.join(a)}" for m, a, _ in ONE_LINE_COMMANDS])
def test_every_failure_of_a_command_is_one_line(module, args, msg, workdir, command, capsys,
                                                monkeypatch):
    monkeypatch.delenv("FLEET_TORCHRL_UNSET_VAR", raising=False)
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        module, args, msg, workdir, command, capsys)


@pytest.mark.parametrize("value", ["abc", "-5", "0", "1.5", " "])
def test_a_bad_run_pid_in_the_environment_is_one_line(value, workdir, command, capsys,
                                                      monkeypatch):
    from fleet_torchrl import evaluate
    from fleet_torchrl.config import RUN_PID

    monkeypatch.setenv(RUN_PID, value)
    before = snapshot(workdir)
    capsys.readouterr()
    assert command(evaluate.main, "eval.n_sims=2", "eval.ticks=10") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {RUN_PID}="), err
    assert snapshot(workdir) == before


def test_composition_errors_are_one_line_on_a_real_command_line(workdir):
    """What a user sees in a shell: exit code 2, one line, no traceback, nothing written."""
    from fleet_torchrl.config import RUN_PID

    before = snapshot(workdir)
    for args, env, msg in ((["~agent"], {}, "agent has no value"),
                           (["=0.5"], {}, "=0.5 is invalid"),
                           (["eval.n_sims=2"], {RUN_PID: "x"}, RUN_PID)):
        r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", *args],
                           cwd=workdir, capture_output=True, text=True, timeout=120,
                           env={**os.environ, **env})
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert lines[0].startswith("error: ") and msg in lines[0], r.stderr
    assert snapshot(workdir) == before


def _terminated_env():
    """An environment of 4 sites stepped until one has failed, and its last tensordict."""
    env = _env(num_sites=4, site=SiteConfig(e_move=5.0, xi=60.0, soc_low=30.0))
    td = env.reset()
    for _ in range(50):
        td = env.step(td.set("action", torch.zeros(4, dtype=torch.int64)))
        if td["next", "terminated"].any():
            return env, env.step_mdp(td)
        td = env.step_mdp(td)
    raise AssertionError("no site failed")


def _load_bad_state(key, change):
    env = _env(num_sites=2)
    env.reset()
    sd = env.state_dict()
    sd[key] = change(sd[key].clone())
    env.load_state_dict(sd)


def _step_terminated():
    env, td = _terminated_env()
    env.step(td.set("action", torch.zeros(4, dtype=torch.int64)))


def _site_ranges(**kw):
    from fleet_torchrl.sim.config import SiteRanges

    return SiteRanges(**kw)


def _train_config(**kw):
    from fleet_torchrl.training.config import TrainConfig

    return TrainConfig(**kw)


ONE_LINE_API = [
    ("SiteConfig(p_c=np.float32(nan))", lambda: SiteConfig(p_c=np.float32("nan"))),
    ("SiteConfig(p_c=np.float64(inf))", lambda: SiteConfig(p_c=np.float64("inf"))),
    ("SiteConfig(e_move=np.float32(-inf))", lambda: SiteConfig(e_move=np.float32("-inf"))),
    ("SiteConfig(p_c=torch nan)", lambda: SiteConfig(p_c=torch.tensor(float("nan")))),
    ("SiteConfig(p_c=True)", lambda: SiteConfig(p_c=True)),
    ("SiteConfig(n_vehicles=np.int64(99))", lambda: SiteConfig(n_vehicles=np.int64(99))),
    ("MDPConfig(gamma=np.float32(nan))", lambda: MDPConfig(gamma=np.float32("nan"))),
    ("SiteRanges(n_vehicles=[1, 3.0])", lambda: _site_ranges(n_vehicles=[1, 3.0])),
    ("SiteRanges(t_c=[10, 20.5])", lambda: _site_ranges(t_c=[10, 20.5])),
    ("SiteRanges(p_c=[0.1, np.float32(nan)])",
     lambda: _site_ranges(p_c=[0.1, np.float32("nan")])),
    ("TrainConfig(max_episodes=10**18)", lambda: _train_config(max_episodes=10**18)),
    ("TrainConfig(defer_margins=[np nan])",
     lambda: _train_config(defer_margins=[np.float64("nan")])),
    ("env device=nope", lambda: _env(device="nope")),
    ("env device=cuda:nope", lambda: _env(device="cuda:x")),
    *([("env device=cuda", lambda: _env(device="cuda")),
       ("env device=torch.device(cuda)", lambda: _env(device=torch.device("cuda")))]
      if _no_device("cuda") else []),
    *([("env device=mps", lambda: _env(device="mps"))] if _no_device("mps") else []),
    ("env step after termination", _step_terminated),
    ("env load nan soc", lambda: _load_bad_state("site.soc", lambda v: v.fill_(float("nan")))),
    ("env load negative seed", lambda: _load_bad_state("seed", lambda v: torch.tensor(-1))),
    ("env load soc 1e9", lambda: _load_bad_state("site.soc", lambda v: v.fill_(1e9))),
    ("env load pos off the site", lambda: _load_bad_state("site.pos", lambda v: v.fill_(99))),
    ("env load wrong shape", lambda: _load_bad_state("site.tick", lambda v: v[:1])),
    ("env load float ticks", lambda: _load_bad_state("site.tick", lambda v: v.double())),
    ("env load negative episodes", lambda: _load_bad_state("episodes", lambda v: v - 5)),
    ("env load p_c inf", lambda: _load_bad_state("site.params.p_c",
                                                 lambda v: v.fill_(float("inf")))),
    ("env never starts", lambda: _env(num_sites=64, site=SiteConfig(
        n_nodes=62, n_vehicles=1, closed_node=20, e_move=100.0)).reset()),
]


@pytest.mark.parametrize("make", [m for _, m in ONE_LINE_API], ids=[n for n, _ in ONE_LINE_API])
def test_every_failure_of_the_python_api_is_one_value_error(make):
    test_the_python_api_refuses_bad_input_with_a_value_error(make)


def test_the_env_names_the_device_and_what_is_allowed():
    with pytest.raises(ValueError, match=r"^device='nope' is invalid: allowed cpu, cuda"):
        _env(device="nope")
    if _no_device("cuda"):
        with pytest.raises(ValueError, match=r"^device='cuda' is invalid: CUDA is not "):
            _env(device="cuda")


def test_a_refused_state_changes_nothing():
    """A loaded state is checked whole before any of it is taken."""
    env = _env(num_sites=2)
    env.reset()
    sd = env.state_dict()
    before = {k: v.clone() for k, v in sd.items()}
    bad = {**sd, "site.pos": sd["site.pos"].clone(), "site.soc": sd["site.soc"].clone().fill_(
        float("nan"))}
    bad["site.pos"].fill_(0)  # taken first, were the state not checked whole
    with pytest.raises(ValueError, match=r"site\.soc"):
        env.load_state_dict(bad)
    assert all(torch.equal(v, before[k]) for k, v in env.state_dict().items())
