"""Gymnasium environments for torque-controlled concentric tube robots (torchpvs physics).

Importing this package registers:

* ``torchpvs/CTRReachForce-v0`` — actions are actuator forces and torques (``Box(-1, 1, (2N,))``
  scaled by the robot's measured force/torque scales), overdamped carriages;
* ``torchpvs/CTRReachForceRobust-v0`` — compensated force actions on a plant that differs
  from the nominal robot in every episode (tube properties +-10 %, an unknown tip force,
  tip-measurement noise; :mod:`envs.plant`), 150 steps per episode;
* ``torchpvs/CTRReachJoint-v0`` — the same robot with joint-increment actions (at most 1 mm and
  5 deg per step), the convention of the CTR reinforcement-learning literature;

all goal-conditioned (Dict observations, ``compute_reward`` for HER), 100 steps per episode
(150 on the robust task, 200 with joint actions),
each with a natively batched ``gymnasium.vector.VectorEnv`` as its ``vector_entry_point``
(``gym.make_vec(id, num_envs=B, vectorization_mode="vector_entry_point")``,
:class:`envs.CTRReachVectorEnv`). ``envs.CTRReachVecEnv`` is the same batch as a
Stable-Baselines3 ``VecEnv``; it is imported on first use, so ``import envs`` needs only
Gymnasium (and torchpvs).

Controllers read the robots through ``state()`` on any of the three (a :class:`RobotState` of
copies: actuation, velocities, elastic forces, tip, goal, margin, warm start, damping, scales).
"""

from gymnasium.envs.registration import register, registry

from .dynamics import CarriageModel, RobotBatch
from .reach_env import CTRReachEnv
from .robots import ROBOTS, Robot, fig3_two_tube, make_robot, rvim_three_tube
from .task import ReachConfig, RobotState
from .vector import CTRReachVectorEnv

# (CTRReachVecEnv, the SB3 adapter, is an attribute loaded on first use: see __getattr__.)
__all__ = ["CTRReachEnv", "CTRReachVectorEnv", "CarriageModel", "ReachConfig", "Robot",
           "RobotBatch", "RobotState", "ROBOTS", "make_robot", "fig3_two_tube", "rvim_three_tube",
           "ENV_IDS", "ENV_OPTIONS", "env_kwargs"]

MAX_EPISODE_STEPS = 100
ENV_IDS = {"torchpvs/CTRReachForce-v0": "force", "torchpvs/CTRReachJoint-v0": "joint",
           "torchpvs/CTRReachForceRobust-v0": "force"}
#: Task options an id fixes beside its control. The robust task: each episode's plant differs
#: from the nominal robot the controllers know (precurvature, E, G +-10 %, an unknown tip
#: force up to 0.5 N, 0.1 mm tip-measurement noise), compensated force actions, and episodes
#: long enough (150 steps) that time is not what limits a good controller.
ENV_OPTIONS = {"torchpvs/CTRReachForceRobust-v0": {
    "compensation": True, "plant_scale": 0.1, "tip_force": 0.5, "tip_noise": 1e-4}}
#: Episode lengths: 100 steps unless set here. Joint actions move at most 1 mm and 5 deg per
#: step: in 100 steps only 65 % of goals' sampled preimages were within reach (89 % of the rest
#: insertion-limited); 200 steps, as in the joint-action literature (Iyengar et al.), give the
#: share that benchmarks/env_ceilings.py prints.
EPISODE_STEPS = {"torchpvs/CTRReachForceRobust-v0": 150, "torchpvs/CTRReachJoint-v0": 200}


def env_kwargs(env_id: str) -> dict:
    """What the registered ``env_id`` fixes: ``control``, its task options and
    ``max_episode_steps`` (the keywords of the batched envs)."""
    if env_id not in ENV_IDS:
        raise ValueError(f"env must be one of {sorted(ENV_IDS)}, got {env_id!r}")
    return {"control": ENV_IDS[env_id], **ENV_OPTIONS.get(env_id, {}),
            "max_episode_steps": EPISODE_STEPS.get(env_id, MAX_EPISODE_STEPS)}


# the entry points fix the id's control: gym.make(force id, control="joint") raises
for _id, _control in ENV_IDS.items():
    if _id not in registry:
        register(id=_id, entry_point=f"envs.reach_env:make_{_control}_env",
                 vector_entry_point=f"envs.vector:make_{_control}_vector_env",
                 max_episode_steps=EPISODE_STEPS.get(_id, MAX_EPISODE_STEPS),
                 kwargs={"control": _control, **ENV_OPTIONS.get(_id, {})})


def __getattr__(name: str):
    # The SB3 adapter imports stable-baselines3: only when asked for.
    if name == "CTRReachVecEnv":
        from .vec_env import CTRReachVecEnv
        return CTRReachVecEnv
    raise AttributeError(f"module 'envs' has no attribute {name!r}")
