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
    return {"policy": "x", "seed": 0, "n_sims": n, "ticks": 100, "site": {"name": "default"},
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
    raw = bytearray(src.read_bytes())  # a byte flipped in the file itself: a weight's
    raw[_member_span(bytes(raw), "data/0")[0]] ^= 0xFF  # (not the zip's padding)
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
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*TINY, f"train.out_dir={tmp_path / 'policy'}"])
    tr = Trainer(RunSpec.of(cfg), tmp_path / "run")
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
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*TINY, "train.max_episodes=1", f"train.out_dir={tmp_path / 'p'}"])
    with caplog.at_level("WARNING"):
        Trainer(RunSpec.of(cfg), tmp_path / "run")
    said = [r.getMessage() for r in caplog.records if "train.max_episodes=1" in r.getMessage()]
    assert len(said) == 1 and "16 episodes" in said[0] and "\n" not in said[0], said


def test_a_second_process_cannot_train_in_a_held_run_folder(tmp_path):
    """A run folder is held by the process that trains in it: a second process (e.g. a
    training left running by a killed ``make table`` beside the one that resumes it) stops
    with one line naming the holder, before it writes anything; the hold ends with its
    process however it ends, and the same process may hold the folder again."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.training import RunSpec, Trainer
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
            Trainer(RunSpec.of(cfg), tmp_path)
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


# ---- compare validates its files' schema and refuses non-finite or overflowing figures
def _compare_files(w: Path) -> None:
    """Results that overflow, are not finite, nest thousands deep or name no site, beside
    ``good.json`` (of the ``workdir`` fixture's helper ``_result``, which names a site)."""
    good = _result()

    def rec(**kw):
        return {**good, "records": {**good["records"], **kw}}

    files = {
        "overflow": rec(trips=[10**400, 11, 12]),  # Python reads it as a 401-digit int
        "inf_trips": rec(trips=[float("inf"), 11, 12]),  # written as Infinity
        "huge_trips": rec(trips=[1e12, 11, 12]),  # finite, beyond any simulation
        "fraction": rec(trips=[10.5, 11, 12]),
        "queue_overflow": rec(queue=[0, 10**30, 0]),
        "failed_two": rec(failed=[0, 2, 0]),
        "no_queue": {**good, "records": {k: v for k, v in good["records"].items()
                                         if k != "queue"}},
        "no_site": {k: v for k, v in good.items() if k != "site"},
        "null_site": {**good, "site": None},
        "empty_site": {**good, "site": {}},
        "deep_site": {**good, "site": {"a": {"b": {"c": {"d": {"e": 1}}}}}},
        "seed_overflow": {**good, "seed": 10**400},
        "sims_overflow": {**good, "n_sims": 10**400},
        "name_newline": {**good, "policy": "x\nerror: forged"},
        "other_seed": {**good, "seed": 1},
        "a_comparison": {"kind": "fleet-compare", "rows": []},
    }
    for name, value in files.items():
        (w / f"{name}.json").write_text(json.dumps(value))
    (w / "deep.json").write_text("[" * 100_000 + "]" * 100_000)  # RecursionError in json
    (w / "deep_dict.json").write_text('{"a":' * 100_000 + "1" + "}" * 100_000)
    (w / "digits.json").write_text('{"policy": "x", "seed": ' + "9" * 5000 + "}")


COMPARE_BAD = [
    (["result=overflow.json", "baseline=good.json"], "records.trips[0]"),
    (["result=good.json", "baseline=inf_trips.json"], "records.trips[0]=inf"),
    (["result=huge_trips.json", "baseline=good.json"], "records.trips[0]"),
    (["result=fraction.json", "baseline=good.json"], "records.trips[0]=10.5"),
    (["result=queue_overflow.json", "baseline=good.json"], "records.queue[1]"),
    (["result=failed_two.json", "baseline=good.json"], "records.failed[1]"),
    (["result=no_queue.json", "baseline=good.json"], "records.queue"),
    (["result=no_site.json", "baseline=good.json"], "missing site"),
    (["result=no_site.json", "baseline=no_site.json"], "missing site"),
    (["result=good.json", "baseline=null_site.json"], "site=None"),
    (["result=empty_site.json", "baseline=good.json"], "site={}"),
    (["result=deep_site.json", "baseline=good.json"], "site="),
    (["result=seed_overflow.json", "baseline=good.json"], "seed="),
    (["result=sims_overflow.json", "baseline=good.json"], "n_sims="),
    (["result=name_newline.json", "baseline=good.json"], "policy="),
    (["result=deep.json", "baseline=good.json"], "deep.json is not valid JSON"),
    (["result=good.json", "baseline=deep_dict.json"], "nested too deeply"),
    (["result=digits.json", "baseline=good.json"], "digits.json is not valid JSON"),
    # several results: every one pairs with the baseline, named if not
    (["results=[good.json,other_seed.json]", "baseline=good.json"],
     "other_seed.json cannot be paired with the baseline good.json: seed differs (1 vs 0)"),
    (["results=[good.json,overflow.json]", "baseline=good.json"], "overflow.json"),
    (["results=[]", "baseline=good.json"], "results=[]"),
    (["result=good.json", "results=[good.json]", "baseline=good.json"], "results="),
    # out: checked before any file is read, never over an input or a file of another kind
    (["result=good.json", "baseline=good.json", "out=taken.json"], "out="),
    (["result=good.json", "baseline=good.json", "out=cmp.txt"], "out="),
    (["result=good.json", "baseline=good.json", "out=/proc/cmp.json"], "out="),
    (["result=good.json", "baseline=good.json", "out=afile/cmp.json"], "out="),
    (["result=deep.json", "baseline=good.json", "out=good.json", "overwrite=true"],
     "a file being compared"),
    (["result=good.json", "baseline=good.json", "out=a_comparison.json"], "overwrite=true"),
    (["result=good.json", "baseline=good.json", "out=number.json", "overwrite=true"],
     "no comparison"),
    (["result=good.json", "baseline=good.json", "out="], "out"),
]


@pytest.mark.parametrize("args,msg", COMPARE_BAD, ids=[" ".join(a) for a, _ in COMPARE_BAD])
def test_compare_refuses_bad_files_in_one_line_and_writes_nothing(args, msg, workdir, command,
                                                                   capsys):
    _compare_files(workdir)
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        "compare", args, msg, workdir, command, capsys)


def test_compare_files_that_overflow_or_nest_are_refused_by_the_python_api(tmp_path):
    from fleet_torchrl.evaluation.results import compare, gain_over, load_result
    from fleet_torchrl.utils.runinfo import read_json

    _compare_files(tmp_path)
    (tmp_path / "good.json").write_text(json.dumps(_result()))
    for name in ("overflow", "inf_trips", "huge_trips", "queue_overflow", "no_site",
                 "null_site", "seed_overflow", "sims_overflow", "deep", "deep_dict", "digits"):
        with pytest.raises(ValueError) as e:
            load_result(tmp_path / f"{name}.json")
        assert "\n" not in str(e.value) and f"{name}.json" in str(e.value), name
        assert len(str(e.value)) < 300, name  # a 400-digit figure is quoted, not dumped
    with pytest.raises(ValueError, match="nested too deeply"):
        read_json(tmp_path / "deep.json")
    # two results that name no site pair with nothing (they would compare equal)
    no_site = {k: v for k, v in _result().items() if k != "site"}
    with pytest.raises(ValueError, match="names no site"):
        gain_over(no_site, no_site)
    g = compare(tmp_path / "good.json", tmp_path / "good.json")
    assert g["gain_pct"] == 0.0 and math.isfinite(g["gain_ci95"])


@pytest.mark.parametrize("name", ["deep.json", "overflow.json"])
def test_compare_on_deep_or_overflowing_json_is_one_line_from_the_command_line(name, workdir):
    _compare_files(workdir)
    before = snapshot(workdir)
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.compare", f"result={name}",
                        "baseline=good.json", "out=cmp.json"], cwd=workdir,
                       capture_output=True, text=True, timeout=120)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"error: {name}") and "Traceback" not in r.stderr
    assert r.stdout == "" and snapshot(workdir) == before


# ---- integrity of everything a decision depends on
def _member_span(raw: bytes, name: str) -> tuple[int, int]:
    """Where the stored bytes of the zip member whose name ends with ``/name`` lie in the
    file ``raw`` (``torch.save`` stores its members uncompressed)."""
    import struct
    import zipfile

    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        info = next(i for i in z.infolist() if i.filename.endswith("/" + name))
    h = info.header_offset
    n, m = struct.unpack("<HH", raw[h + 26:h + 30])
    start = h + 30 + n + m
    return start, start + info.file_size


def _rewrite(src: Path, dst: Path, rehash: bool = False, **fields) -> Path:
    """Write to ``dst`` the policy file ``src`` with some fields of its saved dict replaced
    (a callable is given the old value), its hashes left as they were unless ``rehash``
    (recomputed: what an edit that also forged the hashes, or an older file, looks like)."""
    from fleet_torchrl.agents.policy_files import (
        CONTENT_KEY,
        HASH_KEY,
        content_sha256,
        tensors_sha256,
    )

    bundle = torch.load(src, weights_only=True)
    for key, value in fields.items():
        bundle[key] = value(bundle[key]) if callable(value) else value
    if rehash:
        bundle[HASH_KEY] = tensors_sha256(bundle["state_dict"])
        bundle[CONTENT_KEY] = content_sha256(bundle)
    buf = io.BytesIO()
    torch.save(bundle, buf)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(buf.getvalue())
    return dst


def _refused(path: Path, match: str) -> str:
    from fleet_torchrl.agents import load_policy_file

    with pytest.raises(ValueError, match=match) as e:
        load_policy_file(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg and len(msg) < 400, msg
    return msg


def _bump(value):
    """A value one step away from ``value``: another number, another string (one
    character changed), a dict with its first entry bumped or, if empty, one entry."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, str):
        return chr(ord(value[0]) ^ 1) + value[1:]
    if isinstance(value, dict):
        if not value:
            return {"x": 1}
        key = sorted(value)[0]
        return {**value, key: _bump(value[key])}
    raise TypeError(value)


SAVED_KINDS = ["tabular", "dqn_partial", "search", "imitation", "generalist", "generalist_dqn"]


@pytest.mark.parametrize("name", SAVED_KINDS)
def test_a_changed_spec_or_metadata_is_refused_by_the_hash(name, tmp_path, saved_policies):
    """Every field a decision depends on is covered by the file's hash: its spec (each
    field), its metadata, its kind and its encoding, edited in the saved dict or as one
    flipped byte of the file, are refused with one line."""
    from fleet_torchrl.agents import load_policy_file, save_policy

    src = saved_policies / name / "policy.pt"
    policy = load_policy_file(src)  # the file as saved loads
    kind = torch.load(src, weights_only=True)["kind"]
    src = save_policy(tmp_path / "meta" / "policy.pt", policy, kind,
                      meta={"seed": 3, "note": "trained"})[0]
    bundle = torch.load(src, weights_only=True)
    hashed = "its content does not match its hash .spec or metadata changed"
    edits = {f"spec.{k}": {"spec": {**bundle["spec"], k: _bump(v)}}
             for k, v in bundle["spec"].items()}
    edits["spec (added field)"] = {"spec": {**bundle["spec"], "extra": 1}}
    edits["meta.seed"] = {"meta": {**bundle["meta"], "seed": 4}}
    edits["meta.note"] = {"meta": {**bundle["meta"], "note": "trainee"}}
    edits["kind"] = {"kind": "dqn" if kind != "dqn" else "imitation"}
    edits["encoding"] = {"encoding": "all"}
    for what, change in edits.items():
        msg = _refused(_rewrite(src, tmp_path / f"{what}.pt", **change), hashed)
        assert "retrain" in msg, what
    # one flipped bit in each character of the spec's and metadata's text in the file
    raw = src.read_bytes()
    start, end = _member_span(raw, "data.pkl")
    tokens = [b"partial", b"trained", b"seed", *(k.encode() for k in bundle["spec"])]
    flipped = 0
    for token in tokens:
        at = raw.index(token, start, end)
        for i in range(at, at + len(token)):
            bad = bytearray(raw)
            bad[i] ^= 0x01
            (tmp_path / "flip.pt").write_bytes(bytes(bad))
            _refused(tmp_path / "flip.pt", "")
            flipped += 1
    assert flipped >= 15


def test_an_edited_encoding_is_refused_in_one_line(tmp_path, saved_policies):
    """``spec.encoding`` edited (the hashes forged to match, as an older file would have
    none): refused at load, where it gave a matrix-shape traceback at evaluation; and an
    encoding of another width on the declared side too."""
    src = saved_policies / "dqn_partial" / "policy.pt"
    spec = lambda enc: lambda s: {**s, "encoding": enc}  # noqa: E731
    _refused(_rewrite(src, tmp_path / "a.pt", spec=spec("all")),
             "does not match its hash")
    _refused(_rewrite(src, tmp_path / "b.pt", rehash=True, spec=spec("all")),
             "spec.encoding='all' disagrees with the file's declared encoding 'partial'")
    _refused(_rewrite(src, tmp_path / "c.pt", rehash=True, spec=spec("all"), encoding="all"),
             "the encoding's feature count must match the network's input width: "
             "state=all has 6 to 63 features")
    _refused(_rewrite(src, tmp_path / "d.pt", rehash=True, spec=spec("partial_site"),
                      encoding="partial_site"),
             "state=partial_site has 6 features, the network reads spec.n_obs=3")
    _refused(_rewrite(src, tmp_path / "e.pt", rehash=True, encoding="bogus"),
             "the encoding must be a known one")
    _refused(_rewrite(src, tmp_path / "f.pt", rehash=True, encoding=["partial"]),
             "its encoding must be a string")


@pytest.mark.parametrize("kind", [["dqn"], {"dqn": 1}, 3, None, "rule", "nonexistent"])
def test_a_kind_that_names_no_learner_is_refused_in_one_line(kind, tmp_path, saved_policies):
    src = saved_policies / "dqn_partial" / "policy.pt"
    _refused(_rewrite(src, tmp_path / "k.pt", kind=kind), "does not match its hash")
    msg = _refused(_rewrite(src, tmp_path / "k2.pt", rehash=True, kind=kind),
                   "kind must be a string naming a known policy kind")
    assert "tabular, dqn, search, imitation" in msg


def test_a_spec_too_large_is_refused_before_anything_is_allocated(tmp_path, saved_policies,
                                                                   monkeypatch):
    """A spec asking for width 20000 (800 million weights at depth 3) is refused without
    building a real network: the only networks built are on the ``meta`` device (shapes,
    no memory), and the refusal names the fields; one that would fit is still refused
    because the stored tensors are not of its shapes."""
    import time

    from fleet_torchrl.agents.dqn import learner as dqn

    built = []
    real = dqn.relu_mlp

    def watch(*args, **kw):
        built.append(torch.get_default_device().type)
        return real(*args, **kw)

    monkeypatch.setattr(dqn, "relu_mlp", watch)
    src = saved_policies / "dqn_partial" / "policy.pt"
    net = lambda **kw: lambda s: {**s, "network": {**s["network"], **kw}}  # noqa: E731
    t0 = time.perf_counter()
    _refused(_rewrite(src, tmp_path / "w.pt", rehash=True, spec=net(width=20000, depth=3)),
             r"asks for 800,160,002 parameters.*spec\.network\.width and spec\.network\.depth")
    _refused(_rewrite(src, tmp_path / "w1.pt", rehash=True, spec=net(width=20000)),
             r"qnet\.0\.\w+ is torch.float32 \[8.* in its weights but torch.float32 \[20000")
    _refused(_rewrite(src, tmp_path / "w2.pt", rehash=True, spec=net(width=10**9)),
             r"spec\.network\.width=1000000000 is invalid")
    assert time.perf_counter() - t0 < 5.0
    assert built and set(built) == {"meta"}, built
    for change, match in [(net(width="8"), r"spec\.network\.width='8' is invalid"),
                          (net(depth=2.5), r"spec\.network\.depth=2\.5 is invalid"),
                          (net(bogus=1), r"spec\.network\.bogus is not a setting"),
                          (lambda s: {**s, "n_obs": -3}, r"spec\.n_obs=-3 is invalid"),
                          (lambda s: {**s, "n_obs": True}, r"spec\.n_obs=True is invalid"),
                          (lambda s: {**s, "bogus": 1}, r"spec\.bogus is not a field"),
                          (lambda s: {**s, "anchor": "x"}, r"spec\.anchor='x' is invalid"),
                          (lambda s: [s], "its spec must be a dict")]:
        _refused(_rewrite(src, tmp_path / "s.pt", rehash=True, spec=change), match)


@pytest.mark.parametrize("action", [5, -1, 2])
def test_an_action_table_outside_pass_and_charge_is_refused(action, tmp_path, saved_policies):
    """A search table with action 5 or -1 evaluated as "always charge"; a tabular Q-table
    with more than two actions (a column for action 5) or a negative visit count: refused
    at load, naming the file and the entry; a search table like it is not saved."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.search import SearchPolicy

    def set_cell(state):
        state = {k: v.clone() for k, v in state.items()}
        state["charge"][17] = action
        return state

    src = saved_policies / "search" / "policy.pt"
    _refused(_rewrite(src, tmp_path / "s.pt", rehash=True, state_dict=set_cell),
             rf"charge\[17\] = {action}: an action table holds 0 \(pass\) or 1 \(charge\)")
    _refused(_rewrite(src, tmp_path / "s2.pt", state_dict=set_cell), "do not match the hash")
    pol = SearchPolicy("table")
    pol.charge[3] = action
    with pytest.raises(ValueError, match=rf"charge\[3\] = {action}.*nothing was written"):
        save_policy(tmp_path / "never" / "policy.pt", pol, "search")
    assert not (tmp_path / "never").exists()

    tab = saved_policies / "tabular" / "policy.pt"
    wide = lambda s: {**s, "q": torch.zeros(200, abs(action) + 2)}  # noqa: E731
    _refused(_rewrite(tab, tmp_path / "t.pt", rehash=True, state_dict=wide),
             rf"q is torch.float32 \[200, {abs(action) + 2}\] in its weights but "
             r"torch.float32 \[200, 2\] by its spec")
    neg = lambda s: {**s, "visits": s["visits"].clone().fill_(-abs(action))}  # noqa: E731
    _refused(_rewrite(tab, tmp_path / "t2.pt", rehash=True, state_dict=neg),
             rf"visits\[0, 0\] = {-abs(action)}: a visit count is >= 0")
    as_float = lambda s: {**s, "charge": s["charge"].double()}  # noqa: E731
    _refused(_rewrite(src, tmp_path / "s3.pt", rehash=True, state_dict=as_float),
             r"charge is torch.float64 \[200\] in its weights but torch.int64")


def _bad_policy_files(w: Path, saved: Path) -> None:
    """Bad policy files in the working directory ``w`` for the command cases below."""
    src = saved / "dqn_partial" / "policy.pt"
    net = lambda **kw: lambda s: {**s, "network": {**s["network"], **kw}}  # noqa: E731
    _rewrite(src, w / "meta_changed" / "policy.pt", meta={"seed": 9})
    _rewrite(src, w / "encoding" / "policy.pt", rehash=True,
             spec=lambda s: {**s, "encoding": "all"})
    _rewrite(src, w / "kind" / "policy.pt", rehash=True, kind=["dqn"])
    _rewrite(src, w / "wide" / "policy.pt", rehash=True, spec=net(width=20000, depth=3))
    table = saved / "search" / "policy.pt"
    five = lambda s: {**s, "charge": s["charge"].clone().fill_(5)}  # noqa: E731
    _rewrite(table, w / "table5" / "policy.pt", rehash=True, state_dict=five)
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.imitation import ImitationPolicy

    save_policy(w / "all16" / "policy.pt", ImitationPolicy(16, "all", 8, 1), "imitation")


POLICY_COMMANDS = [
    (["agent=dqn", "agent.policy=meta_changed"], "its content does not match its hash"),
    (["agent=dqn", "agent.policy=encoding"], "disagrees with the file's declared encoding"),
    (["agent=dqn", "agent.policy=kind"], "kind must be a string naming a known policy kind"),
    (["agent=dqn", "agent.policy=wide"], "spec.network.width and spec.network.depth"),
    (["agent=search", "agent.policy=table5/policy.pt"], "charge[0] = 5"),
    (["agent=imitation", "state=all", "agent.policy=all16", "site.n_nodes=10"],
     "state=all has 11 features on this site (site.n_nodes=10), the network reads 16"),
]


@pytest.mark.parametrize("args,msg", POLICY_COMMANDS, ids=[a[-1] for a, _ in POLICY_COMMANDS])
def test_evaluate_refuses_a_bad_policy_file_in_one_line(args, msg, workdir, saved_policies,
                                                        command, capsys):
    _bad_policy_files(workdir, saved_policies)
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        "evaluate", args, msg, workdir, command, capsys)


def test_the_evaluate_command_line_refuses_a_changed_policy_file(workdir, saved_policies):
    """What a user sees: ``python -m fleet_torchrl.evaluate agent=dqn agent.policy=<a file
    whose spec was edited>`` says one line and exits 2."""
    _bad_policy_files(workdir, saved_policies)
    test_real_command_lines_say_one_line_and_exit_2(
        ["fleet_torchrl.evaluate", "agent=dqn", "agent.policy=encoding"],
        "disagrees with the file's declared encoding", workdir)


# ---- publishing never overwrites (issue 48, item 1; concurrency tests of item 7)
# a tabular run that fails no evaluation site (published) and one that fails them all (not)
PUB_OK = [*TINY, "train.eval_ticks=40", "train.eval_seed=4"]
PUB_FAILS = TINY
EVAL = ["eval.n_sims=4", "eval.ticks=50", "eval.progress=false", "eval.backend=eager"]


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def _sha(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_seeds_publish_to_their_own_folders_and_no_run_replaces_a_policy(tmp_path, monkeypatch,
                                                                        command, capsys):
    """``fleet-train -m seed=0,1`` publishes each seed to ``<name>/seed<s>/``; a later run
    onto a published policy (other settings, or the same training) is refused before it
    starts, in one line naming the folder, and the policy's bytes stay; two jobs of a
    multirun on one ``train.out_dir`` are refused before either starts;
    ``train.overwrite=true`` replaces."""
    from fleet_torchrl import train

    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.train", "-m", *PUB_OK,
                        "seed=0,1", "hydra.launcher.n_jobs=1"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    pol = tmp_path / "results" / "policies" / "tabular"
    assert sorted(p.name for p in pol.iterdir()) == ["seed0", "seed1"]
    for seed in (0, 1):
        summary = json.loads((pol / f"seed{seed}" / "train_summary.json").read_text())
        assert summary["published"] and summary["fingerprint"]["seed"] == seed
        assert summary["policy_sha256"] == _sha(pol / f"seed{seed}" / "policy.pt")
    sha = _sha(pol / "seed0" / "policy.pt")
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    capsys.readouterr()
    for extra, msg in ((["mdp.p_f=2000"], "of another training (mdp.p_f"),
                       ([], "of this same training")):
        assert command(train.main, *PUB_OK, *extra) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert msg in line and str(Path("results/policies/tabular/seed0")) in line, line
        assert "train.overwrite=true" in line
        assert snapshot(tmp_path) == before  # no run folder either
    assert _sha(pol / "seed0" / "policy.pt") == sha
    assert command(train.main, "-m", *PUB_OK, "seed=3,4", "train.out_dir=shared") == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "seed=3 and seed=4" in line and str(tmp_path / "shared") in line, line
    assert snapshot(tmp_path) == before
    assert command(train.main, *PUB_OK, "mdp.p_f=2000", "train.overwrite=true") == 0
    summary = json.loads((pol / "seed0" / "train_summary.json").read_text())
    assert summary["fingerprint"]["mdp"]["p_f"] == 2000.0
    assert summary["policy_sha256"] == _sha(pol / "seed0" / "policy.pt") != sha


@pytest.mark.slow
def test_a_run_that_failed_sites_publishes_nothing(tmp_path, monkeypatch, command):
    """A run whose best policy failed evaluation sites keeps it in its run folder; the log
    says so in one line; nothing appears under the policies folder."""
    from fleet_torchrl import train

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    assert command(train.main, *PUB_FAILS, f"hydra.run.dir={run}") == 0
    assert not (tmp_path / "results").exists()
    summary = json.loads((run / "train_summary.json").read_text())
    assert summary["published"] is False and summary["best"]["failure_rate"] > 0
    assert summary["policy"] == str(run / "policy.pt")
    assert summary["policy_sha256"] == _sha(run / "policy.pt")
    said = [ln for ln in (run / "train.log").read_text().splitlines() if "not published" in ln]
    assert len(said) == 1 and "failed" in said[0] and str(run / "policy.pt") in said[0], said


def test_two_evaluations_on_one_output_are_refused_before_either_starts(workdir, command,
                                                                       capsys):
    from fleet_torchrl import evaluate

    before = snapshot(workdir)
    assert command(evaluate.main, "-m", "agent=rule,heuristic", "eval.out=x.json", *EVAL) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "agent=rule and agent=heuristic" in line and "x.json" in line, line
    assert snapshot(workdir) == before


@pytest.mark.parametrize("target", ["unrelated", "summary", "fifo", "csv"])
def test_an_eval_out_that_is_no_result_is_refused_and_kept(target, workdir, command, capsys):
    """An ``eval.out`` holding an unrelated JSON, a published policy's
    ``train_summary.json`` or a FIFO, or beside a CSV that is no result's, is refused in one
    line; the file stays as it was."""
    from fleet_torchrl import evaluate

    path = workdir / "out.json"
    if target == "unrelated":
        path.write_text('{"my": "notes"}')
    elif target == "summary":
        path.write_text(json.dumps({"name": "tabular", "best": {"trips": 1.0},
                                    "policy_sha256": "ab" * 32}))
    elif target == "fifo":
        os.mkfifo(path)
    else:
        (workdir / "out.csv").write_text("a,b\n1,2\n")
    before = snapshot(workdir)
    kept = None if target == "fifo" else (path if path.exists() else workdir / "out.csv")
    content = kept.read_bytes() if kept else None
    assert command(evaluate.main, "agent=rule", "eval.out=out.json", *EVAL,
                   "eval.overwrite=true") == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "eval.out=" in line and "out." in line, line
    assert snapshot(workdir) == before
    if kept:
        assert kept.read_bytes() == content


def test_an_existing_result_is_replaced_only_with_eval_overwrite(workdir, command, capsys):
    from fleet_torchrl import evaluate
    from fleet_torchrl.evaluation import check_result_pair

    assert command(evaluate.main, "agent=rule", "eval.out=r.json", *EVAL) == 0
    first = (workdir / "r.json").read_bytes()
    assert check_result_pair(workdir / "r.json")["csv"] == "r.csv"
    capsys.readouterr()
    before = snapshot(workdir)
    assert command(evaluate.main, "agent=rule", "eval.out=r.json", *EVAL, "eval.seed=1") == 2
    assert "eval.overwrite=true replaces it" in _one_error_line(capsys.readouterr().err)
    assert snapshot(workdir) == before and (workdir / "r.json").read_bytes() == first
    assert command(evaluate.main, "agent=rule", "eval.out=r.json", *EVAL, "eval.seed=1",
                   "eval.overwrite=true") == 0
    assert check_result_pair(workdir / "r.json")["seed"] == 1


def test_eval_overwrite_is_a_typed_setting():
    from fleet_torchrl.evaluation import EvalConfig
    from fleet_torchrl.training import TrainConfig

    assert EvalConfig().overwrite is False and TrainConfig().overwrite is False
    with pytest.raises(ConfigError, match=r"eval\.overwrite"):
        EvalConfig(overwrite="yes")
    with pytest.raises(ConfigError, match=r"train\.overwrite"):
        TrainConfig(overwrite=1)


@pytest.mark.slow
def test_a_training_in_a_held_folder_is_refused_before_hydra_writes(tmp_path, monkeypatch,
                                                                    command, capsys):
    """A second training, or a resume, started in a run folder where a training runs (held
    by another process) is refused in one line before Hydra rewrites the folder's
    ``.hydra/*.yaml`` and before ``run_info.json``: every byte stays."""
    from fleet_torchrl import train

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    common = [*PUB_FAILS, f"hydra.run.dir={run}"]
    assert command(train.main, *common) == 0
    files = [run / ".hydra" / n for n in ("config.yaml", "overrides.yaml", "hydra.yaml")]
    files.append(run / "run_info.json")
    content = {f: f.read_bytes() for f in files}
    code = ("import sys, time; from fleet_torchrl.utils.paths import hold_run_dir; "
            "hold_run_dir(sys.argv[1]); print('held', flush=True); time.sleep(600)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(tmp_path)
        capsys.readouterr()
        for extra in (["seed=7", "train.out_dir=elsewhere"], ["resume=true"]):
            assert command(train.main, *common, *extra) == 2
            line = _one_error_line(capsys.readouterr().err)
            assert f"in use by process {holder.pid}" in line, line
            assert snapshot(tmp_path) == before
            assert {f: f.read_bytes() for f in files} == content
    finally:
        holder.kill()
        holder.wait()


def test_a_multirun_job_whose_folder_is_held_is_refused_before_any_job(tmp_path, monkeypatch,
                                                                       command, capsys):
    """A multirun's jobs hold their folders in their own processes, after Hydra has written
    ``.hydra/`` there: the launching command refuses a job whose folder another process
    holds now, in one line, before any job starts or writes."""
    from fleet_torchrl import train

    monkeypatch.chdir(tmp_path)
    sweep = tmp_path / "sweep"
    (sweep / "job").mkdir(parents=True)
    code = ("import sys, time; from fleet_torchrl.utils.paths import hold_run_dir; "
            "hold_run_dir(sys.argv[1]); print('held', flush=True); time.sleep(600)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(sweep / "job")],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(tmp_path)
        capsys.readouterr()
        assert command(train.main, "-m", *PUB_FAILS, f"hydra.sweep.dir={sweep}",
                       "hydra.sweep.subdir=job") == 2
        line = _one_error_line(capsys.readouterr().err)
        assert f"in use by process {holder.pid}" in line, line
        assert snapshot(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()


_STALL = """
import os, sys, time
real = os.fsync
def fsync(fd):
    real(fd)
    name = os.readlink(f"/proc/self/fd/{fd}")
    if os.path.basename(name).startswith("." + os.environ["STALL_ON"] + "."):
        print("stalled", flush=True)
        time.sleep(600)
os.fsync = fsync
from fleet_torchrl.evaluate import main
sys.argv = ["fleet-evaluate", *sys.argv[1:]]
main()
"""


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")
def test_an_evaluation_killed_mid_write_leaves_no_temp_file_and_no_mixed_pair(tmp_path,
                                                                              monkeypatch,
                                                                              command):
    """``kill -9`` of an evaluation while it writes its result: killed between its new CSV
    and its JSON, the old JSON beside the new CSV is detected (never silently used); the
    next evaluation of the same result leaves no ``.tmp`` behind and a consistent pair."""
    from fleet_torchrl import evaluate
    from fleet_torchrl.evaluation import check_result_pair

    monkeypatch.chdir(tmp_path)
    out = ["agent=rule", "eval.out=r.json", *EVAL]
    assert command(evaluate.main, *out) == 0
    old_json = (tmp_path / "r.json").read_bytes()
    for stall_on in ("r.json", "r.csv"):
        p = subprocess.Popen([sys.executable, "-c", _STALL, *out, "eval.seed=1",
                              "eval.overwrite=true", "hydra.run.dir=killed"],
                             cwd=tmp_path, stdout=subprocess.PIPE, text=True,
                             env={**os.environ, "STALL_ON": stall_on})
        try:
            for line in p.stdout:  # until the write stalls (the process waits there)
                if line.strip() == "stalled":
                    break
            else:
                pytest.fail("the evaluation ended before it wrote its result")
        finally:
            p.kill()  # SIGKILL: no cleanup runs
            p.wait()
        assert list(tmp_path.glob(f".{stall_on}.*.tmp"))  # what the kill left
        assert (tmp_path / "r.json").read_bytes() == old_json
        if stall_on == "r.json":  # the new CSV beside the old JSON: told apart
            with pytest.raises(ValueError, match="does not belong to"):
                check_result_pair(tmp_path / "r.json")
        assert command(evaluate.main, *out, "eval.seed=2", "eval.overwrite=true") == 0
        assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))
        assert check_result_pair(tmp_path / "r.json")["seed"] == 2
        old_json = (tmp_path / "r.json").read_bytes()


# ---- paths stay inside their roots
# names that become parts of paths are plain names; a computed policy folder that is a
# symbolic link out of table.policies_dir is not followed unless asked; an empty or
# unwritable run folder and a name too long for the file system are refused before the run
# folder is made
TOO_LONG = "n" * 300
PATH_COMMANDS = [
    ("evaluate", ["site.name=/../../../../tmp/x"], "site.name"),
    ("train", ["agent=dqn", "site.name=/../../../../tmp/x"], "site.name"),
    ("evaluate", ["site.name=../eval/default"], "site.name"),
    ("evaluate", ["site.name=..", "agent=dqn"], "site.name"),
    ("evaluate", [f"site.name={TOO_LONG}"], "site.name"),
    ("train", ["agent=tabular", f"site.name={TOO_LONG}"], "site.name"),
    ("evaluate", ["hydra.run.dir="], "hydra.run.dir"),
    ("train", ["agent=tabular", "hydra.run.dir="], "hydra.run.dir"),
    ("evaluate", ["hydra.run.dir=/proc/x"], "hydra.run.dir"),
    ("evaluate", [f"hydra.run.dir={TOO_LONG}"], "hydra.run.dir"),
    ("evaluate", [f"hydra.run.dir=runs/{TOO_LONG}/x"], "hydra.run.dir"),
    ("evaluate", [f"eval.out={TOO_LONG}.json"], "eval.out"),
    ("evaluate", [f"eval.out={'e' * 250}.json"], "eval.out"),  # no room for its .tmp file
    ("train", ["agent=tabular", f"train.out_dir={TOO_LONG}"], "train.out_dir"),
    ("evaluate", ["--multirun", "agent=rule,heuristic", "hydra.sweep.dir="], "hydra.sweep.dir"),
    ("evaluate", ["--multirun", "agent=rule,heuristic", "hydra.sweep.subdir="],
     "hydra.sweep.subdir"),
    ("sweeps", ["sweep.name=../x"], "sweep.name"),
    ("sweeps", ["sweep.name=/tmp/x"], "sweep.name"),
    ("policy_maps", ["maps.planner_sites=[../eval/default]"], "maps.planner_sites[0]"),
    ("evaluate", [f"+recipes.{TOO_LONG}={{overrides:['agent=tabular']}}"], "too long a name"),
    ("evaluate", [f"{TOO_LONG}=1"], "too long a name"),
    # the file tools: Hydra makes their run folder too
    ("compare", ["result=good.json", "baseline=good.json", "hydra.run.dir=/proc/x"],
     "hydra.run.dir"),
    ("compare", ["result=good.json", "baseline=good.json", "hydra.run.dir="], "hydra.run.dir"),
    ("report", ["results=.", "hydra.run.dir=/proc/x"], "hydra.run.dir"),
    ("grid", ["sweep_dir=runs", f"hydra.run.dir={TOO_LONG}"], "hydra.run.dir"),
    ("sweeps_summary", ["hydra.run.dir="], "hydra.run.dir"),
    ("sweeps_summary", ["name=../../eval/default"], "name="),
]


@pytest.mark.parametrize("module,args,msg", PATH_COMMANDS,
                         ids=[f"{m}:{' '.join(a)[:60]}" for m, a, _ in PATH_COMMANDS])
def test_a_path_that_would_escape_or_fail_is_refused_in_one_line(
        module, args, msg, workdir, command, capsys):
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        module, args, msg, workdir, command, capsys)


def test_a_recipe_name_too_long_for_a_folder_is_refused(workdir, command, capsys):
    """A recipe becomes folder names (``<policies>/<recipe>/seed<s>``, ``train_<recipe>_*``)."""
    (workdir / "conf" / "recipes").mkdir(parents=True)
    (workdir / "conf" / "recipes" / "long.yaml").write_text(
        f"defaults: [default, _self_]\n{'r' * 100}:\n  overrides: [agent=tabular]\n")
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        "table", ["recipes=long"], "at most 64 characters", workdir, command, capsys)


@pytest.fixture
def linked_policies(workdir, saved_policies):
    """``results/policies/dqn_partial`` in the working directory: a symbolic link to a saved
    policy's folder outside ``results/``."""
    root = workdir / "results" / "policies"
    root.mkdir(parents=True)
    (root / "dqn_partial").symlink_to(saved_policies / "dqn_partial")
    return root


@pytest.mark.parametrize("module,args", [
    ("evaluate", ["agent=dqn", "table.policies_dir=results/policies"]),
    ("train", ["agent=dqn", "table.policies_dir=results/policies"]),
], ids=["evaluate", "train"])
def test_a_policy_folder_linked_out_of_results_is_refused(
        module, args, linked_policies, workdir, command, capsys):
    """Evaluating reads, training publishes: neither follows the link out of results/."""
    test_a_command_refuses_bad_input_in_one_line_and_writes_nothing(
        module, args, "table.follow_symlinks=true", workdir, command, capsys)


def test_a_policy_folder_linked_out_is_read_when_asked(linked_policies, workdir, command,
                                                       saved_policies, capsys):
    from fleet_torchrl import evaluate

    small = ["agent=dqn", "table.policies_dir=results/policies", "eval.n_sims=2",
             "eval.ticks=20", "hydra.run.dir=run"]
    assert command(evaluate.main, *small, "table.follow_symlinks=true",
                   "eval.out=followed.json") == 0
    assert json.loads((workdir / "followed.json").read_text())["n_sims"] == 2
    # the link named as the policy itself: the user's own path, read as it is
    assert command(evaluate.main, *small, f"agent.policy={linked_policies / 'dqn_partial'}",
                   "eval.out=named.json") == 0
    assert (workdir / "named.json").is_file()
    assert sorted(p.name for p in (saved_policies / "dqn_partial").iterdir()) == ["policy.pt"]


@pytest.mark.parametrize("path,kind,words", [
    ("", "dir", "''"), ("", "file", "''"), ("n" * 256, "dir", "folder name"),
    ("n" * 242, "file", "file name"), (f"a/{'n' * 300}/b", "dir", "folder name"),
    ("/" + "d/" * 2100, "dir", "path is"),
])
def test_output_paths_too_long_or_empty_are_refused(path, kind, words, workdir):
    from fleet_torchrl.utils.paths import check_output

    before = snapshot(workdir)
    with pytest.raises(ConfigError) as e:
        check_output("x.out", path, kind)
    assert str(e.value).startswith("x.out") and words in str(e.value)
    assert "\n" not in str(e.value) and snapshot(workdir) == before
    assert check_output("x.out", "n" * 241, "file") and check_output("x.out", "n" * 255, "dir")


PATH_CLI = [
    (["fleet_torchrl.compare", "result=good.json", "baseline=good.json",
      "hydra.run.dir=/proc/x"], "hydra.run.dir"),
    (["fleet_torchrl.evaluate", "hydra.run.dir="], "hydra.run.dir"),
]


@pytest.mark.parametrize("argv,msg", PATH_CLI, ids=[" ".join(a) for a, _ in PATH_CLI])
def test_real_command_lines_refuse_bad_run_folders(argv, msg, workdir):
    test_real_command_lines_say_one_line_and_exit_2(argv, msg, workdir)


API_NAMES = [
    ("SiteConfig(name='../x')", lambda: SiteConfig(name="../x")),
    ("SiteConfig(name='/tmp/x')", lambda: SiteConfig(name="/tmp/x")),
    ("SiteConfig(name='')", lambda: SiteConfig(name="")),
    ("SiteConfig(name=300 chars)", lambda: SiteConfig(name=TOO_LONG)),
    ("env site name ../x", lambda: _env(site={"name": "../eval/default"})),
]


@pytest.mark.parametrize("make", [m for _, m in API_NAMES], ids=[n for n, _ in API_NAMES])
def test_the_python_api_refuses_a_site_name_that_is_no_name(make):
    test_the_python_api_refuses_bad_input_with_a_value_error(make)


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


# ---- typed run specs: each command checks the groups it reads


def test_a_bad_setting_of_a_group_a_command_does_not_read_is_ignored(workdir, command):
    """evaluate reads no sweep, maps or bench: bad values there neither stop it nor change
    its result; sweeps, which reads them, refuses the same value in one line."""
    from fleet_torchrl import evaluate, sweeps

    out = workdir / "rule.json"
    assert command(evaluate.main, "sweep.param=bogus", "bench.batches=[0]", "maps.out=afile",
                   "eval.n_sims=2", "eval.ticks=50", "eval.progress=false",
                   f"eval.out={out}", f"hydra.run.dir={workdir / 'run'}") == 0
    assert json.loads(out.read_text())["n_sims"] == 2
    before = snapshot(workdir)
    assert command(sweeps.main, "sweep.param=bogus", f"hydra.run.dir={workdir / 'run2'}") == 2
    assert snapshot(workdir) == before


# ---- agents from outside: an entry point or a user's conf/agent YAML naming a schema
def _broken_entry_point(w: Path) -> None:
    info = w / "lib" / "broken_agent-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken_agent\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[fleet_torchrl.agents]\nbroken = broken_agent.config:Nope\n")


def _no_schema_yaml(w: Path) -> None:
    (w / "conf" / "agent").mkdir(parents=True)
    (w / "conf" / "agent" / "odd.yaml").write_text("_schema_: collections:OrderedDict\n")


OUTSIDE_AGENTS = [
    (_broken_entry_point, "error: the entry point broken = broken_agent.config:Nope (group "
     "fleet_torchrl.agents) cannot be imported: ModuleNotFoundError: No module named "
     "'broken_agent'; fix or uninstall its package"),
    (_no_schema_yaml, "error: conf/agent/odd.yaml: _schema_='collections:OrderedDict' is "
     "invalid: allowed a dataclass extending fleet_torchrl.agents.AgentConfig (the agent's "
     "schema), not <class 'collections.OrderedDict'>"),
]


@pytest.mark.parametrize("make,msg", OUTSIDE_AGENTS, ids=["entry point", "conf yaml"])
def test_an_agent_from_outside_that_is_no_agent_is_one_line(make, msg, tmp_path):
    """Every command refuses to start, in one line naming where the agent came from, and
    writes nothing."""
    make(tmp_path)
    before = snapshot(tmp_path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path / "lib"), str(Path(__file__).resolve().parents[1]),
         os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.evaluate", "agent=rule"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2, r.stderr[-2000:]
    assert r.stderr.strip().splitlines() == [msg]
    assert snapshot(tmp_path) == before
