"""The Gymnasium and Stable-Baselines3 adapters (optional extra: pip install -e '.[gym]')."""

from __future__ import annotations

import numpy as np
import pytest
import torch

gymnasium = pytest.importorskip("gymnasium")


def test_single_site_env_passes_the_gymnasium_and_sb3_checkers():
    from gymnasium.utils.env_checker import check_env

    from fleet_torchrl.env.gym import FleetGymEnv

    env = FleetGymEnv()
    check_env(env, skip_render_check=True)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3.check_env(FleetGymEnv(), warn=True)


def test_single_site_env_is_the_torchrl_env():
    """Same seed, same actions: the adapter reports what FleetChargingEnv computes."""
    from fleet_torchrl.env import FleetChargingEnv
    from fleet_torchrl.env.gym import GYM_ID

    env = gymnasium.make(GYM_ID, encoding="all")
    obs, info = env.reset(seed=3)
    ref = FleetChargingEnv(encoding="all", num_sites=1, seed=3)
    td = ref.reset()
    assert np.array_equal(obs, td["observation"][0].numpy())
    for k in range(30):
        action = k % 3 == 0
        obs, reward, term, trunc, info = env.step(int(action))
        td = ref.step(td.set("action", torch.tensor([int(action)])))
        assert np.array_equal(obs, td["next", "observation"][0].numpy())
        assert reward == pytest.approx(float(td["next", "reward"][0, 0]))
        assert term == bool(td["next", "terminated"][0, 0])
        if term or trunc:
            break
        td = ref.step_mdp(td)
    assert info["ticks"] > 0


def test_torchrl_gym_env_builds_the_registered_env():
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    from fleet_torchrl.env.gym import GYM_ID

    env = GymEnv(GYM_ID)
    check_env_specs(env)
    assert env.rollout(20)["next", "reward"].shape == (20, 1)


@pytest.mark.slow
def test_vectorised_env_trains_sb3_dqn():
    sb3 = pytest.importorskip("stable_baselines3")
    from fleet_torchrl.env.gym import FleetVecEnv

    venv = FleetVecEnv(num_sites=16, seed=0)
    obs = venv.reset()
    assert obs.shape == (16, 3) and obs.dtype == np.float32
    done_seen = False
    for _ in range(400):
        obs, rew, done, infos = venv.step(np.ones(16, dtype=np.int64) * 0)  # always pass: fails
        if done.any():
            i = int(np.flatnonzero(done)[0])
            assert "terminal_observation" in infos[i] and not infos[i]["TimeLimit.truncated"]
            done_seen = True
            break
    assert done_seen
    model = sb3.DQN("MlpPolicy", FleetVecEnv(num_sites=16, seed=1), learning_starts=200,
                    buffer_size=5000, train_freq=4, seed=0, device="cpu")
    model.learn(total_timesteps=3000)
    act, _ = model.predict(obs, deterministic=True)
    assert act.shape == (16,)


def test_gymnasium_and_torchrl_build_the_env_with_nothing_imported_first():
    """A fresh interpreter: ``gymnasium.make`` and TorchRL's ``GymEnv`` given the module id
    import and register the env themselves (Gymnasium 1.x loads no plugin entry points)."""
    import subprocess
    import sys

    code = (
        "import sys, gymnasium\n"
        "from torchrl.envs import GymEnv\n"
        "assert not any(m.startswith('fleet_torchrl') for m in sys.modules)\n"
        "env = gymnasium.make('fleet_torchrl.env.gym:FleetCharging-v0', encoding='all')\n"
        "obs, _ = env.reset(seed=0)\n"
        "assert obs.shape == (16,), obs.shape\n"
        "td = GymEnv('fleet_torchrl.env.gym:FleetCharging-v0').rollout(5)\n"
        "assert td['next', 'reward'].shape == (5, 1)\n"
        "assert gymnasium.make('FleetCharging-v0').observation_space.shape == (3,)\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_registration_is_lazy_and_idempotent():
    from fleet_torchrl.env.gym import GYM_ID, GYM_MODULE_ID, register_envs

    spec = gymnasium.spec(GYM_ID)
    assert spec.entry_point == "fleet_torchrl.env.gym:FleetGymEnv"  # built only by make
    assert GYM_MODULE_ID == "fleet_torchrl.env.gym:FleetCharging-v0"
    register_envs()
    assert gymnasium.spec(GYM_ID) is spec
