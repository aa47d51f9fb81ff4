"""StackThree: robosuite's Stack with a third cube, a MimicGen-style longer-horizon variant of it.

robosuite's Stack asks for the red cube (A, 4 cm) on the green one (B, 5 cm). StackThree adds a blue cube (C, 4 cm)
and asks for the tower B (bottom), A, C (top), released. It changes Stack in these ways, and nothing else:

- the third cube is placed by Stack's own placement sampler (uniform in the same 16 cm square of the table, any yaw,
  no two cubes' footprints overlapping), drawn from the env's ``rng`` after A and B, so a reset stays a function of
  the seed that `carp.tasks.arms.simulation.reset_env` gives that generator;
- ``object-state`` keeps Stack's 23 values first (A's pose, B's pose, A to B, gripper to A, gripper to B) and appends,
  in Stack's convention for C, C's position (3) and xyzw quaternion (4), ``cubeC_to_cubeA`` (A's position minus C's,
  3: as Stack's ``cubeA_to_cubeB`` points from the cube to carry to the cube it goes on) and ``gripper_to_cubeC``
  (3): 36 values;
- success is Stack's (A touches B, lifted clear of the table, not grasped) and C touches A with its centre above A's
  top face, and the gripper touches neither A nor C: a tower still held, or whose top cube a finger still rests on,
  has not been released;
- the reward is sparse only (``reward_scale`` on success, else 0): Stack's shaped reward measures A and B alone, so a
  shaped StackThree is refused rather than rewarded for the first pair.

MimicGen (Mandlekar et al., 2023) has a three-cube stacking task of this kind; this env is written on robosuite
1.5.2's Stack, not taken from it. Importing this module registers ``StackThree`` with robosuite (its environments'
metaclass registers every subclass by class name), so ``robosuite.make("StackThree", ...)`` works from then on;
the task's ``make_env``
(`carp.tasks.arms.task.RobosuiteArmTask`) imports it before building one.
"""

import numpy as np
from robosuite.environments.manipulation.stack import Stack
from robosuite.models.objects import BoxObject
from robosuite.utils.mjcf_utils import CustomMaterial
from robosuite.utils.observables import Observable, sensor
from robosuite.utils.transform_utils import convert_quat

CUBE_C_HALF_SIZE_M = 0.02
"""Half the edge of the third cube, as Stack's cube A: a tower narrowing upwards, each cube on one at least as wide."""


class StackThree(Stack):
    """robosuite's Stack with a third (blue) cube C; success is the tower B, A, C released.

    Takes Stack's arguments; ``reward_shaping`` must stay False.

    Raises:
        ValueError: ``reward_shaping=True``.
    """

    def __init__(self, *args, **kwargs) -> None:
        if kwargs.get("reward_shaping", False):
            raise ValueError("StackThree has a sparse reward only; Stack's shaped reward would measure cubes A and B")
        super().__init__(*args, **kwargs)

    def _load_model(self) -> None:
        super()._load_model()
        bluewood = CustomMaterial(
            texture="WoodBlue",
            tex_name="bluewood",
            mat_name="bluewood_mat",
            tex_attrib={"type": "cube"},
            mat_attrib={"texrepeat": "1 1", "specular": "0.4", "shininess": "0.1"},
        )
        self.cubeC = BoxObject(
            name="cubeC",
            size_min=[CUBE_C_HALF_SIZE_M] * 3,
            size_max=[CUBE_C_HALF_SIZE_M] * 3,
            rgba=[0, 0, 1, 1],
            material=bluewood,
        )
        # Stack's sampler (its own, or the one passed as placement_initializer) now holds A and B; C joins it so that
        # one sample places all three apart, drawing from the same seeded generator.
        self.placement_initializer.add_objects(self.cubeC)
        # Task.merge_objects adds the body but not the object list that contact and id lookups read.
        self.model.mujoco_objects.append(self.cubeC)
        self.model.merge_objects([self.cubeC])

    def _setup_references(self) -> None:
        super()._setup_references()
        self.cubeC_body_id = self.sim.model.body_name2id(self.cubeC.root_body)

    def _setup_observables(self):
        observables = super()._setup_observables()
        if not self.use_object_obs:
            return observables
        modality = "object"

        @sensor(modality=modality)
        def cubeC_pos(obs_cache):
            return np.array(self.sim.data.body_xpos[self.cubeC_body_id])

        @sensor(modality=modality)
        def cubeC_quat(obs_cache):
            return convert_quat(np.array(self.sim.data.body_xquat[self.cubeC_body_id]), to="xyzw")

        @sensor(modality=modality)
        def cubeC_to_cubeA(obs_cache):
            if "cubeA_pos" in obs_cache and "cubeC_pos" in obs_cache:
                return obs_cache["cubeA_pos"] - obs_cache["cubeC_pos"]
            return np.zeros(3)

        sensors = [cubeC_pos, cubeC_quat, cubeC_to_cubeA]
        arm_prefixes = self._get_arm_prefixes(self.robots[0], include_robot_name=False)
        full_prefixes = self._get_arm_prefixes(self.robots[0])
        sensors += [
            self._get_obj_eef_sensor(full_prefix, "cubeC_pos", f"{arm_prefix}gripper_to_cubeC", modality)
            for arm_prefix, full_prefix in zip(arm_prefixes, full_prefixes, strict=True)
        ]
        # Appended after Stack's observables, so object-state keeps Stack's 23 values first.
        for sensor_function in sensors:
            name = sensor_function.__name__
            observables[name] = Observable(name=name, sensor=sensor_function, sampling_rate=self.control_freq)
        return observables

    def reward(self, action=None) -> float:
        """``reward_scale`` (1 when None) once the tower stands released, else 0."""
        scale = 1.0 if self.reward_scale is None else self.reward_scale
        return scale if self._check_success() else 0.0

    def _check_success(self) -> bool:
        """Stack's success for A on B, C resting on A, and the gripper touching neither A nor C."""
        if not super()._check_success():
            return False
        cube_a = self.sim.data.body_xpos[self.cubeA_body_id]
        cube_c = self.sim.data.body_xpos[self.cubeC_body_id]
        cube_a_half = self.cubeA.size[2]
        c_on_a = cube_c[2] - cube_a[2] > cube_a_half and self.check_contact(self.cubeC, self.cubeA)
        if not c_on_a:
            return False
        grippers = self.robots[0].gripper.values()
        return not any(self.check_contact(gripper, cube) for gripper in grippers for cube in (self.cubeA, self.cubeC))
