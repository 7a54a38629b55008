"""moonhaul's phase environments for Python trainers.

``PhaseVecEnv(config="configs/train/lift.toml", num_envs=N, seed=S)`` is an rsl_rl ``VecEnv``
over the same environment ``moonhaul-train`` trains (``moonhaul_env::task::make_env``: same
observation function, action pipeline and rewards). ``moonhaul.rsl`` holds the runner that
trains it with stock rsl_rl on one process or many (``torchrun``); ``moonhaul.export`` writes
a trained actor as moonhaul's onboard policy file, which ``OnboardPolicy`` reads and runs as
the robot does.
"""

from ._native import Env, OnboardPolicy, __version__
from .vec_env import PhaseVecEnv

__all__ = ["Env", "OnboardPolicy", "PhaseVecEnv", "__version__"]
