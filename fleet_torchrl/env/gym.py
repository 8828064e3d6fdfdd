"""The decision process for the Gymnasium and Stable-Baselines3 ecosystems (``pip install -e
'.[gym]'``): thin adapters over :class:`~fleet_torchrl.env.FleetChargingEnv`, with the same
observations, rewards and flags (one step = one decision epoch, MODEL §2).

* :class:`FleetGymEnv`: a ``gymnasium.Env`` of one site (``Box(0, 1, (F,))`` observations,
  ``Discrete(2)`` actions: 0 pass, 1 charge), registered as ``FleetCharging-v0``.
  ``gymnasium.make("fleet_torchrl.env.gym:FleetCharging-v0", site=..., encoding=...)`` and
  TorchRL's ``GymEnv("fleet_torchrl.env.gym:FleetCharging-v0")`` build it with nothing
  imported first (Gymnasium imports the module named before the colon, which registers the
  id); after this module is imported the bare ``FleetCharging-v0`` works too. Gymnasium 1.x
  has no plugin entry points (they went in 1.0), so no installed package can register an id
  without being imported. ``reset(seed=s)`` restarts the stream of training sites of seed
  ``s`` (common random numbers: the same seed, the same sites).
* :class:`FleetVecEnv`: a Stable-Baselines3 ``VecEnv`` over ``num_sites`` sites stepped
  together by the batched simulator; a site whose episode ends restarts at once and reports
  its last observation as ``infos[i]["terminal_observation"]`` and a tick-budget end as
  ``infos[i]["TimeLimit.truncated"]``, as SB3's own vectorised environments do.

Inside TorchRL, use :class:`FleetChargingEnv` directly: it already is a batched ``EnvBase``.

Both adapters check what they are given with the environment's own rules
(:func:`~fleet_torchrl.env.fleet_env.check_actions`): an action is ``0`` (pass) or ``1``
(charge) as an integer or a boolean (a float only if exactly ``0.0`` or ``1.0``), one per
site; ``0.7``, NaN, ``2``, ``-1`` raise a one-line ``ValueError`` (never ``int(0.7) == 0``,
never "anything non-zero charges"). Seeds are integers in ``[0, 2**32 - 1]``; ``site`` and
``mdp`` may be given as dicts of their fields (``gymnasium.make(GYM_ID, site={"p_c": 0.6})``).
"""

from __future__ import annotations

from typing import Any

try:
    import gymnasium
    from gymnasium import spaces
except ImportError:  # one line that says what to install, not a traceback into gymnasium
    raise ImportError("fleet_torchrl.env.gym needs Gymnasium, in the gym extra: "
                      "pip install 'fleet_torchrl[gym]' (in a checkout: pip install -e "
                      "'.[gym]')") from None
import numpy as np

from ..sim import SiteConfig
from .config import MDPConfig
from .fleet_env import FleetChargingEnv, check_actions, check_seed

GYM_ID = "FleetCharging-v0"
#: the id that needs no import first: Gymnasium imports the module, which registers GYM_ID
GYM_MODULE_ID = f"{__name__}:{GYM_ID}"


def _spaces(env: FleetChargingEnv) -> tuple[spaces.Box, spaces.Discrete]:
    n = env.observation_spec["observation"].shape[-1]
    return spaces.Box(0.0, 1.0, shape=(n,), dtype=np.float32), spaces.Discrete(2)


def _info(td, i: int = 0) -> dict[str, Any]:
    return {k: int(td[k][i, 0]) for k in ("trips", "queue_ticks", "ticks")}


class FleetGymEnv(gymnasium.Env):
    """One charging site as a Gymnasium environment (see the module docstring)."""

    metadata = {"render_modes": []}

    def __init__(self, site: SiteConfig | None = None, encoding: str = "partial",
                 mdp: MDPConfig | None = None, seed: int = 0) -> None:
        self.env = FleetChargingEnv(site=site, encoding=encoding, num_sites=1, mdp=mdp,
                                    seed=seed)
        self.observation_space, self.action_space = _spaces(self.env)
        self._td = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            seed = check_seed(seed)
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        self._td = self.env.reset()
        return self._td["observation"][0].numpy().copy(), _info(self._td)

    def step(self, action):
        if self._td is None:
            raise RuntimeError("call reset() before step()")
        td = self._td.set("action", check_actions(action, 1))
        td = self.env.step(td)
        nxt = td["next"]
        obs = nxt["observation"][0].numpy().copy()
        terminated = bool(nxt["terminated"][0, 0])
        truncated = bool(nxt["truncated"][0, 0])
        self._td = self.env.step_mdp(td)
        return obs, float(nxt["reward"][0, 0]), terminated, truncated, _info(nxt)


try:  # Stable-Baselines3 is optional within the gym extra's users
    from stable_baselines3.common.vec_env import VecEnv
except ImportError:  # pragma: no cover - exercised only without SB3
    VecEnv = None

    def FleetVecEnv(*args: Any, **kwargs: Any) -> Any:  # stands for the class
        raise ImportError("FleetVecEnv needs Stable-Baselines3, in the gym extra: "
                          "pip install 'fleet_torchrl[gym]'")


if VecEnv is not None:

    class FleetVecEnv(VecEnv):
        """``num_sites`` charging sites as one Stable-Baselines3 ``VecEnv``."""

        def __init__(self, num_sites: int = 8, site: SiteConfig | None = None,
                     encoding: str = "partial", mdp: MDPConfig | None = None,
                     seed: int = 0) -> None:
            self.env = FleetChargingEnv(site=site, encoding=encoding, num_sites=num_sites,
                                        mdp=mdp, seed=seed)
            obs_space, act_space = _spaces(self.env)
            super().__init__(num_sites, obs_space, act_space)
            self._td = None
            self._actions = None

        def reset(self):
            seed = self._seeds[0] if getattr(self, "_seeds", None) and \
                self._seeds[0] is not None else None
            if seed is not None:
                self.env.set_seed(check_seed(seed))
            if hasattr(self, "_reset_seeds"):
                self._reset_seeds()
            self._td = self.env.reset()
            return self._td["observation"].numpy().copy()

        def step_async(self, actions) -> None:
            if self._td is None:
                raise RuntimeError("call reset() before step()")
            self._actions = check_actions(actions, self.num_envs, "actions")

        def step_wait(self):
            td = self._td.set("action", self._actions)
            td, root = self.env.step_and_maybe_reset(td)
            nxt = td["next"]
            done = nxt["done"][:, 0].numpy().copy()
            trunc = nxt["truncated"][:, 0].numpy()
            last = nxt["observation"].numpy()
            infos: list[dict[str, Any]] = [_info(nxt, i) for i in range(self.num_envs)]
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = last[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(trunc[i])
            self._td = root
            return (root["observation"].numpy().copy(), nxt["reward"][:, 0].numpy().copy(),
                    done, infos)

        def close(self) -> None:
            pass

        def get_attr(self, attr_name: str, indices=None) -> list[Any]:
            return [getattr(self, attr_name)] * len(self._indices(indices))

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            setattr(self, attr_name, value)

        def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list[Any]:
            return [getattr(self, method_name)(*args, **kwargs)] * len(self._indices(indices))

        def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
            return [False] * len(self._indices(indices))

        def _indices(self, indices) -> list[int]:
            if indices is None:
                return list(range(self.num_envs))
            return [indices] if isinstance(indices, int) else list(indices)


def register_envs() -> None:
    """Register ``FleetCharging-v0`` with Gymnasium (idempotent). The entry point is a
    string, so a registry that lists the id does not build anything until ``make``."""
    if GYM_ID not in gymnasium.registry:
        gymnasium.register(id=GYM_ID, entry_point=f"{__name__}:FleetGymEnv")


register_envs()

__all__ = ["GYM_ID", "GYM_MODULE_ID", "FleetGymEnv", "FleetVecEnv", "register_envs"]
