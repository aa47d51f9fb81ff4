"""Threading: pass a needle's tip through a ring held up by a tripod fixed on the table, a MimicGen-style precise task.

The scene is robosuite's table with the Panda (as in Lift) and two objects built from robosuite's `CompositeObject`:

- the needle (`NeedleObject`), free on the table: a handle (a 7 x 2.4 x 3 cm box) with a thin bar (12 cm long, 8 mm
  square) sticking out of one end on the handle's axis; its body frame is the centre of its bounding box, with x from
  the handle towards the tip;
- the ring tripod (`RingTripodObject`), fixed: a vertical ring (inner radius 20 mm, outer 30 mm, 1 cm deep, sixteen
  boxes around a circle) whose centre is 11 cm above the table, on three legs that meet under the ring and spread
  to the table. The ring's axis is the tripod body's x-axis.

The needle's bar is 8 mm across, so a bar on the ring's axis has 16 mm of room all round: a bar that enters the ring
with its axis within 16 mm of the ring's passes without touching it.

A reset draws, from the env's ``rng`` (which `carp.tasks.arms.simulation.reset_env` seeds), the tripod's position (x in
[0.10, 0.16] m, y in [0.06, 0.14] m from the table's centre) and yaw (its ring's axis within 30 degrees of +x, away
from the robot), then the needle's position (x in [-0.12, -0.02] m, y in [-0.20, -0.12] m) and yaw (its tip within 60
degrees of +x); the two regions are apart, so the needle never starts under the tripod.

Success: the needle's bar crosses the ring's mid-plane inside the hole and its tip is past the ring's far face: a
needle through the ring from either side counts, a tip that stops in front of the ring or passes beside it does not.
The needle may still be held. The reward is sparse only (``reward_scale`` on success, else 0).

``object-state`` (23 values): the needle's position (3) and xyzw quaternion (4), the ring's centre (3) and xyzw
quaternion (4), ``needle_tip_to_ring`` (the ring's centre minus the tip, 3), ``gripper_to_needle`` (3) and
``gripper_to_ring`` (3), the last two in robosuite's convention (the object's position minus the grip site's).

MimicGen (Mandlekar et al., 2023) has a threading task of this kind; this env is written on robosuite 1.5.2, not
taken from it. Importing this module registers ``Threading`` with robosuite (its environments' metaclass registers
every subclass by class name); the task's ``make_env``
(`carp.tasks.arms.task.RobosuiteArmTask`) imports it before building one.
"""

import math

import numpy as np
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
from robosuite.models.arenas import TableArena
from robosuite.models.objects import CompositeObject
from robosuite.models.tasks import ManipulationTask
from robosuite.utils.observables import Observable, sensor
from robosuite.utils.placement_samplers import SequentialCompositeSampler, UniformRandomSampler
from robosuite.utils.transform_utils import convert_quat

HANDLE_HALF_SIZE_M = (0.035, 0.012, 0.015)
"""Half the handle's length (along the needle), width and height."""
BAR_HALF_LENGTH_M = 0.06
BAR_HALF_WIDTH_M = 0.004
RING_INNER_RADIUS_M = 0.02
RING_OUTER_RADIUS_M = 0.03
RING_HALF_DEPTH_M = 0.005
RING_SEGMENTS = 16
RING_CENTER_HEIGHT_M = 0.11
"""Height of the ring's centre above the table: the held needle passes it with the fingers well clear of the table."""
LEG_RADIUS_M = 0.005
FOOT_DISTANCE_M = 0.06
"""Horizontal distance of each leg's foot from the point under the ring's centre."""
TABLE_OFFSET = (0.0, 0.0, 0.8)


def _quaternion_wxyz_between(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The (w, x, y, z) quaternion of the shortest rotation taking unit vector ``source`` (3,) to ``target`` (3,)."""
    axis = np.cross(source, target)
    quaternion = np.array([1.0 + float(np.dot(source, target)), *axis])
    return quaternion / np.linalg.norm(quaternion)


class NeedleObject(CompositeObject):
    """A handle with a thin bar sticking out of one end, free to move; the body frame is its bounding box's centre.

    Sites: ``tip`` at the bar's free end, on the needle's x-axis.
    """

    def __init__(self, name: str) -> None:
        half_length = HANDLE_HALF_SIZE_M[0] + BAR_HALF_LENGTH_M
        handle_center = -half_length + HANDLE_HALF_SIZE_M[0]
        bar_center = half_length - BAR_HALF_LENGTH_M
        super().__init__(
            name=name,
            total_size=[half_length, HANDLE_HALF_SIZE_M[1], HANDLE_HALF_SIZE_M[2]],
            geom_types=["box", "box"],
            geom_sizes=[list(HANDLE_HALF_SIZE_M), [BAR_HALF_LENGTH_M, BAR_HALF_WIDTH_M, BAR_HALF_WIDTH_M]],
            geom_locations=[(handle_center, 0.0, 0.0), (bar_center, 0.0, 0.0)],
            geom_names=["handle", "bar"],
            geom_rgbas=[(0.2, 0.3, 0.8, 1.0), (0.7, 0.7, 0.7, 1.0)],
            # Light wood: the handle holds the needle's centre of mass, so it lies on the handle, bar off the table.
            density=500.0,
            locations_relative_to_center=True,
            sites=[{"name": "tip", "pos": f"{half_length} 0 0", "size": "0.002", "rgba": "1 0 0 1", "type": "sphere"}],
        )
        self.handle_center_m = handle_center
        """Handle centre along the needle's x-axis, from the body frame's origin."""
        self.tip_m = half_length
        """Tip along the needle's x-axis."""
        self.bar_base_m = half_length - 2 * BAR_HALF_LENGTH_M
        """Where the bar leaves the handle, along the needle's x-axis."""


class RingTripodObject(CompositeObject):
    """A vertical ring on three legs, without joints (fixed where it is put); the ring's axis is the body's x-axis.

    The body frame is the bounding box's centre; the ring's centre is ``ring_center_m`` from it (site ``ring_center``).
    Its collision geoms are named ``ring0`` .. ``ring15`` (the ring) and ``leg0`` .. ``leg2``.
    """

    def __init__(self, name: str) -> None:
        half_height = (RING_CENTER_HEIGHT_M + RING_OUTER_RADIUS_M) / 2
        floor = -half_height
        ring_center = np.array([0.0, 0.0, floor + RING_CENTER_HEIGHT_M])
        types, sizes, locations, quaternions, names = [], [], [], [], []
        # Each segment is a box whose local x is the ring's axis, y points outwards from the centre and z along the
        # circle; half its tangential width closes the polygon at the outer radius.
        radial_half = (RING_OUTER_RADIUS_M - RING_INNER_RADIUS_M) * math.cos(math.pi / RING_SEGMENTS) / 2
        tangential_half = RING_OUTER_RADIUS_M * math.sin(math.pi / RING_SEGMENTS)
        middle_radius = RING_INNER_RADIUS_M * math.cos(math.pi / RING_SEGMENTS) + radial_half
        for index in range(RING_SEGMENTS):
            angle = 2 * math.pi * index / RING_SEGMENTS
            types.append("box")
            sizes.append([RING_HALF_DEPTH_M, radial_half, tangential_half])
            locations.append(tuple(ring_center + middle_radius * np.array([0.0, math.cos(angle), math.sin(angle)])))
            quaternions.append((math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0))
            names.append(f"ring{index}")
        # The legs meet just inside the ring's lowest segment and spread to the table, one behind the ring (+x) and
        # two to the sides towards the robot, away from the needle's path along the axis.
        top = ring_center - np.array([0.0, 0.0, RING_OUTER_RADIUS_M - LEG_RADIUS_M])
        for index, yaw in enumerate((0.0, 2 * math.pi / 3, -2 * math.pi / 3)):
            foot = np.array([FOOT_DISTANCE_M * math.cos(yaw), FOOT_DISTANCE_M * math.sin(yaw), floor + LEG_RADIUS_M])
            direction = (top - foot) / np.linalg.norm(top - foot)
            types.append("capsule")
            sizes.append([LEG_RADIUS_M, float(np.linalg.norm(top - foot)) / 2])
            locations.append(tuple((top + foot) / 2))
            quaternions.append(tuple(_quaternion_wxyz_between(np.array([0.0, 0.0, 1.0]), direction)))
            names.append(f"leg{index}")
        super().__init__(
            name=name,
            total_size=[FOOT_DISTANCE_M, FOOT_DISTANCE_M, half_height],
            geom_types=types,
            geom_sizes=sizes,
            geom_locations=locations,
            geom_quats=quaternions,
            geom_names=names,
            rgba=(0.8, 0.5, 0.2, 1.0),
            locations_relative_to_center=True,
            joints=None,
            sites=[
                {
                    "name": "ring_center",
                    "pos": " ".join(str(value) for value in ring_center),
                    "size": "0.002",
                    "rgba": "0 1 0 1",
                    "type": "sphere",
                }
            ],
        )
        self.ring_center_m = ring_center
        """The ring's centre in the body frame (3,)."""


class Threading(ManipulationEnv):
    """A Panda at robosuite's table threads a needle through a ring on a tripod fixed at a seeded pose.

    Takes `ManipulationEnv`'s arguments (robots, controller_configs, cameras, ...) and these; ``reward_shaping`` must
    stay False.

    Args:
        table_full_size: the table's (x, y, z) size, as in Lift.
        table_friction: the table's friction, as in Lift.
        use_object_obs: whether ``object-state`` is observed.
        reward_scale: the reward on success (None: 1).
        reward_shaping: refused when True.
        initialization_noise: the arm's joint noise at reset, robosuite's default as in Lift (drawn from ``rng``).

    Raises:
        ValueError: ``reward_shaping=True``.
    """

    def __init__(
        self,
        robots,
        table_full_size=(0.8, 0.8, 0.05),
        table_friction=(1.0, 5e-3, 1e-4),
        use_object_obs: bool = True,
        reward_scale: float | None = 1.0,
        reward_shaping: bool = False,
        initialization_noise="default",
        **kwargs,
    ) -> None:
        if reward_shaping:
            raise ValueError("Threading has a sparse reward only")
        self.table_full_size = table_full_size
        self.table_friction = table_friction
        self.table_offset = np.array(TABLE_OFFSET)
        self.use_object_obs = use_object_obs
        self.reward_scale = reward_scale
        self.reward_shaping = reward_shaping
        super().__init__(robots=robots, initialization_noise=initialization_noise, **kwargs)

    def _load_model(self) -> None:
        super()._load_model()
        robot_model = self.robots[0].robot_model
        robot_model.set_base_xpos(robot_model.base_xpos_offset["table"](self.table_full_size[0]))
        arena = TableArena(
            table_full_size=self.table_full_size, table_friction=self.table_friction, table_offset=self.table_offset
        )
        arena.set_origin([0, 0, 0])
        self.needle = NeedleObject("needle")
        self.tripod = RingTripodObject("tripod")
        # A new sampler per model: every reset builds new objects, and its regions are the task's (module docstring).
        self.placement_initializer = self._placement_sampler()
        self.model = ManipulationTask(
            mujoco_arena=arena,
            mujoco_robots=[robot.robot_model for robot in self.robots],
            mujoco_objects=[self.tripod, self.needle],
        )

    def _placement_sampler(self) -> SequentialCompositeSampler:
        sampler = SequentialCompositeSampler(name="ObjectSampler")
        common = dict(
            ensure_object_boundary_in_range=False,
            ensure_valid_placement=True,
            reference_pos=self.table_offset,
            rotation_axis="z",
            rng=self.rng,
        )
        sampler.append_sampler(
            UniformRandomSampler(
                name="TripodSampler",
                mujoco_objects=self.tripod,
                x_range=[0.10, 0.16],
                y_range=[0.06, 0.14],
                rotation=(-math.pi / 6, math.pi / 6),
                z_offset=0.0,
                **common,
            )
        )
        sampler.append_sampler(
            UniformRandomSampler(
                name="NeedleSampler",
                mujoco_objects=self.needle,
                x_range=[-0.12, -0.02],
                y_range=[-0.20, -0.12],
                rotation=(-math.pi / 3, math.pi / 3),
                z_offset=0.001,
                **common,
            )
        )
        return sampler

    def _setup_references(self) -> None:
        super()._setup_references()
        model = self.sim.model
        self.needle_body_id = model.body_name2id(self.needle.root_body)
        self.tripod_body_id = model.body_name2id(self.tripod.root_body)
        self.needle_tip_site_id = model.site_name2id(self.needle.naming_prefix + "tip")
        self.ring_center_site_id = model.site_name2id(self.tripod.naming_prefix + "ring_center")
        self.needle_geom_ids = np.array([model.geom_name2id(name) for name in self.needle.contact_geoms])
        self.ring_geom_ids = np.array(
            [model.geom_name2id(f"{self.tripod.naming_prefix}ring{index}") for index in range(RING_SEGMENTS)]
        )

    def _setup_observables(self):
        observables = super()._setup_observables()
        if not self.use_object_obs:
            return observables
        modality = "object"

        @sensor(modality=modality)
        def needle_pos(obs_cache):
            return np.array(self.sim.data.body_xpos[self.needle_body_id])

        @sensor(modality=modality)
        def needle_quat(obs_cache):
            return convert_quat(np.array(self.sim.data.body_xquat[self.needle_body_id]), to="xyzw")

        @sensor(modality=modality)
        def ring_pos(obs_cache):
            return self.ring_center()

        @sensor(modality=modality)
        def ring_quat(obs_cache):
            return convert_quat(np.array(self.sim.data.body_xquat[self.tripod_body_id]), to="xyzw")

        @sensor(modality=modality)
        def needle_tip_to_ring(obs_cache):
            return self.ring_center() - self.needle_tip()

        sensors = [needle_pos, needle_quat, ring_pos, ring_quat, needle_tip_to_ring]
        arm_prefixes = self._get_arm_prefixes(self.robots[0], include_robot_name=False)
        full_prefixes = self._get_arm_prefixes(self.robots[0])
        for arm_prefix, full_prefix in zip(arm_prefixes, full_prefixes, strict=True):
            sensors.append(
                self._get_obj_eef_sensor(full_prefix, "needle_pos", f"{arm_prefix}gripper_to_needle", modality)
            )
            sensors.append(self._get_obj_eef_sensor(full_prefix, "ring_pos", f"{arm_prefix}gripper_to_ring", modality))
        for sensor_function in sensors:
            name = sensor_function.__name__
            observables[name] = Observable(name=name, sensor=sensor_function, sampling_rate=self.control_freq)
        return observables

    def _reset_internal(self) -> None:
        super()._reset_internal()
        if self.deterministic_reset:
            return
        placements = self.placement_initializer.sample()
        tripod_position, tripod_quaternion, _ = placements[self.tripod.name]
        # The tripod has no joint: its pose is its body's, set in the model (every reset rebuilds the model).
        self.sim.model.body_pos[self.tripod_body_id] = tripod_position
        self.sim.model.body_quat[self.tripod_body_id] = tripod_quaternion
        needle_position, needle_quaternion, _ = placements[self.needle.name]
        self.sim.data.set_joint_qpos(
            self.needle.joints[0], np.concatenate([np.array(needle_position), np.array(needle_quaternion)])
        )

    def needle_tip(self) -> np.ndarray:
        """World position (3,) of the needle's tip."""
        return np.array(self.sim.data.site_xpos[self.needle_tip_site_id])

    def needle_axis(self) -> np.ndarray:
        """World direction (3,) of the needle, a unit vector from the handle towards the tip."""
        return np.array(self.sim.data.body_xmat[self.needle_body_id]).reshape(3, 3)[:, 0]

    def needle_bar_base(self) -> np.ndarray:
        """World position (3,) of the bar's end at the handle, on the needle's axis."""
        return self.needle_tip() - (self.needle.tip_m - self.needle.bar_base_m) * self.needle_axis()

    def ring_center(self) -> np.ndarray:
        """World position (3,) of the ring's centre."""
        return np.array(self.sim.data.site_xpos[self.ring_center_site_id])

    def ring_axis(self) -> np.ndarray:
        """World direction (3,) of the ring's axis (unit): the tripod's x-axis, within 30 degrees of +x."""
        return np.array(self.sim.data.body_xmat[self.tripod_body_id]).reshape(3, 3)[:, 0]

    def reward(self, action=None) -> float:
        """``reward_scale`` (1 when None) once the needle is through the ring, else 0."""
        scale = 1.0 if self.reward_scale is None else self.reward_scale
        return scale if self._check_success() else 0.0

    def _check_success(self) -> bool:
        """The bar crosses the ring's mid-plane inside the hole, and the tip is past the ring's far face."""
        center, axis = self.ring_center(), self.ring_axis()
        tip, base = self.needle_tip(), self.needle_bar_base()
        tip_depth = float(np.dot(tip - center, axis))  # signed distance of the tip from the mid-plane
        base_depth = float(np.dot(base - center, axis))
        if abs(tip_depth) <= RING_HALF_DEPTH_M or tip_depth * base_depth >= 0:
            return False
        crossing = base + (tip - base) * (base_depth / (base_depth - tip_depth))
        return bool(np.linalg.norm(crossing - center) < RING_INNER_RADIUS_M)
