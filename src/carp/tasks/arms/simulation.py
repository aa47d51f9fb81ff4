"""The robosuite Panda arm simulation every arm task runs on: env_args, env construction, seeded reset, observations.

An environment is described by robomimic-style ``env_args`` (a JSON-serializable dict stored in every demonstration
file), so that evaluation rebuilds exactly the env the data came from. Two action spaces exist for the Panda's OSC
pose controller in robosuite 1.5:

- ``"absolute"`` (default): the arm part of the composite ``BASIC`` controller gets ``input_type="absolute"`` and
  ``input_ref_frame="world"``; an action is the grip site's world position (3), its world orientation as an
  axis-angle vector (3) and the gripper command (1, -1 open .. 1 closed). This is the format of robomimic's
  ``*_abs`` datasets. robosuite 1.5 ignores the older ``control_delta`` flag, hence the composite config.
- ``"delta"``: robosuite's default delta OSC pose; position and rotation inputs in [-1, 1] scale to 5 cm and
  0.5 rad per control step.
"""

import copy
from collections.abc import Mapping, Sequence

import numpy as np

# robot0_eef_pos (3) + robot0_eef_quat (4) + robot0_gripper_qpos (2), the proprioception used by default.
ROBOT_OBS_DIM = 9
CONTROLLERS = ("absolute", "delta")
ROBOT = "Panda"
CONTROL_FREQUENCY_HZ = 20

# robomimic names robosuite's concatenated object state "object"; the rest of the keys keep robosuite's names.
_ROBOMIMIC_KEY_NAMES = {"object-state": "object"}
_IMAGE_SUFFIXES = ("_image", "_depth", "_segmentation")


def controller_config(controller: str = "absolute") -> dict:
    """Composite controller config for the Panda with absolute (world-frame) or delta arm input.

    Raises:
        ValueError: unknown ``controller``.
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller '{controller}'; expected one of {list(CONTROLLERS)}")
    from robosuite.controllers import load_composite_controller_config

    config = copy.deepcopy(load_composite_controller_config(controller="BASIC", robot=ROBOT))
    # BASIC also configures parts a Panda lacks (left arm, torso, head, base, legs); robosuite drops them with a
    # warning per part on every env creation, so keep only the arm.
    config["body_parts"] = {"right": config["body_parts"]["right"]}
    if controller == "absolute":
        arm = config["body_parts"]["right"]
        arm["input_type"] = "absolute"
        arm["input_ref_frame"] = "world"
    return config


def make_env_args(env_name: str, controller: str = "absolute") -> dict:
    """robomimic-style env_args (JSON-serializable) for a robosuite env and controller.

    Args:
        env_name: robosuite's name of the env class, e.g. ``Lift`` (a task's ``env_name``).
        controller: ``"absolute"`` or ``"delta"``.

    Raises:
        ValueError: unknown controller, naming the value.
    """
    import robosuite

    return {
        "env_name": env_name,
        "type": 1,  # robomimic's EnvType.ROBOSUITE_TYPE
        "env_version": robosuite.__version__,
        "env_kwargs": {
            "robots": ROBOT,
            "controller_configs": controller_config(controller),
            "has_renderer": False,
            "has_offscreen_renderer": False,
            "use_camera_obs": False,
            "reward_shaping": False,
            "control_freq": CONTROL_FREQUENCY_HZ,
            "ignore_done": True,
        },
    }


def controller_kind(env_args: Mapping) -> str:
    """Return ``"absolute"`` or ``"delta"`` for the arm controller described by env_args."""
    configs = env_args["env_kwargs"]["controller_configs"]
    arm = configs["body_parts"]["right"] if "body_parts" in configs else configs
    if arm.get("input_type") == "absolute" or arm.get("control_delta") is False:
        return "absolute"
    return "delta"


def make_env(
    env_args: Mapping,
    render_offscreen: bool = False,
    camera_names: Sequence[str] = (),
    image_size: int = 84,
):
    """Build the robosuite env described by env_args.

    robosuite knows an env class once its defining module has run: robosuite's own always, one carp defines (a task's
    ``env_module``) after its import, which the task's ``make_env`` does before calling this.

    Args:
        env_args: dict from :func:`make_env_args` or a robomimic file's ``data.attrs["env_args"]``.
        render_offscreen: enable the offscreen renderer (videos, image observations).
        camera_names: cameras whose images become observations (``<camera>_image``); empty for low-dim only.
        image_size: height and width of camera observations.

    Returns:
        The robosuite environment (not wrapped).
    """
    import robosuite

    kwargs = copy.deepcopy(dict(env_args["env_kwargs"]))
    use_cameras = len(camera_names) > 0
    kwargs.update(
        has_renderer=False,
        has_offscreen_renderer=render_offscreen or use_cameras,
        use_camera_obs=use_cameras,
    )
    if use_cameras:
        kwargs.update(
            camera_names=list(camera_names),
            camera_heights=image_size,
            camera_widths=image_size,
        )
    return robosuite.make(env_args["env_name"], **kwargs)


def reset_env(env, seed: int) -> dict[str, np.ndarray]:
    """Reset so that the initial state is a function of ``seed`` only.

    robosuite 1.5 draws object placements, object sizes and robot initialization noise from one
    ``numpy.random.Generator`` (``env.rng``) that the placement samplers and objects hold by reference. Re-seeding
    that generator in place (rather than replacing it) reaches every holder, so the same seed gives the same
    initial state whatever ran before.

    Returns:
        The observation dict after the reset.
    """
    env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
    return env.reset()


def is_success(env) -> bool:
    """The env's own task success check."""
    return bool(env._check_success())


def low_dim_observations(obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """All non-image observations as flat float64 arrays, ``object-state`` renamed ``object`` as in robomimic.

    Args:
        obs: a robosuite observation dict.

    Returns:
        key -> (Do_key,) float64 array.
    """
    features = {}
    for key, value in obs.items():
        if key.endswith(_IMAGE_SUFFIXES):
            continue
        features[_ROBOMIMIC_KEY_NAMES.get(key, key)] = np.asarray(value, dtype=np.float64).reshape(-1)
    return features
