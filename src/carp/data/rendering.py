"""Camera images rendered offscreen from stored simulator states.

Images are derived data: as robomimic's ``dataset_states_to_obs`` does, a demo's camera observations are rendered
from its stored MuJoCo states (``data/demo_<i>/states``, robosuite's flattened ``[time, qpos, qvel]``) in the model
the demo was recorded in, so adding a camera or a resolution needs no new collection. The same
:class:`CameraRenderer` renders the live observations of an evaluation episode, so training and evaluation images
come from one function with one set of settings.

Conventions:

- Images are uint8 (H, W, 3) RGB, upright: row 0 is the top of the picture. This is what robomimic's image datasets
  store (robomimic flips robosuite's camera observations, which follow OpenGL's bottom-up row order under robosuite's
  default ``IMAGE_CONVENTION = "opengl"``), so a user's robomimic image file and ours hold the same pictures.
- Each frame is rendered from the state alone: the state is copied into the renderer's own ``MjData`` and
  ``mj_forward`` computes the poses. A live frame and a frame rendered later from the stored state are therefore
  identical, and rendering never touches the simulation it observes.
- As robosuite's cameras, frames show the visual meshes, not the collision geoms.
- Shadows, reflections, the skybox and multisample anti-aliasing are off by default (:class:`RenderSettings`): a
  policy needs none of them and each costs rendering time.

Offscreen OpenGL comes from EGL (headless GPU or Mesa's software driver) or OSMesa. MuJoCo picks its backend from
the ``MUJOCO_GL`` environment variable when ``mujoco`` is first imported; the library never sets it. An entry point
that renders sets it first, e.g. ``os.environ.setdefault("MUJOCO_GL", offscreen_backend())``. Debian packages: EGL in
``libegl1``, ``libegl-mesa0`` and ``libgl1-mesa-dri`` (``make render-deps``), OSMesa in ``libosmesa6``.
"""

import ctypes.util
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

CAMERAS = ("agentview", "robot0_eye_in_hand")
IMAGE_SIZE = 84
# MUJOCO_GL values that render without a display, in order of preference, with the shared library each one loads.
OFFSCREEN_BACKENDS = {"egl": "EGL", "osmesa": "OSMesa"}
# robosuite puts collision geoms in group 0 and visual meshes in group 1, and its cameras show only the visual ones
# (render_collision_mesh=False, render_visual_mesh=True); the other groups keep MuJoCo's defaults.
COLLISION_GEOM_GROUP, VISUAL_GEOM_GROUP = 0, 1


class RenderingError(RuntimeError):
    """Offscreen rendering is unavailable, or a demo cannot be rendered."""


@dataclass(frozen=True)
class RenderSettings:
    """What is rendered and how.

    Attributes:
        cameras: robosuite camera names; each gives the obs key ``<camera>_image``.
        image_size: height and width in pixels (robomimic's image datasets: 84).
        shadows: render shadows.
        reflections: render reflective materials' mirror images.
        skybox: render the skybox.
        anti_aliasing: multisample anti-aliasing with the model's sample count (otherwise one sample per pixel).
    """

    cameras: tuple[str, ...] = CAMERAS
    image_size: int = IMAGE_SIZE
    shadows: bool = False
    reflections: bool = False
    skybox: bool = False
    anti_aliasing: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if not self.cameras or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras={list(self.cameras)}: must name at least one camera, each once")
        if self.image_size < 1:
            raise ValueError(f"image_size={self.image_size}: must be >= 1")

    @property
    def image_keys(self) -> tuple[str, ...]:
        """Obs keys of the cameras' images, in camera order."""
        return tuple(f"{camera}_image" for camera in self.cameras)


def offscreen_backend() -> str:
    """The ``MUJOCO_GL`` value for headless rendering here: ``egl`` if libEGL is installed, else ``osmesa``.

    Raises:
        RenderingError: neither library is installed; names the Debian packages that provide them.
    """
    for backend, library in OFFSCREEN_BACKENDS.items():
        if ctypes.util.find_library(library):
            return backend
    raise RenderingError(
        "no offscreen OpenGL library found (libEGL or libOSMesa); install libegl1, libegl-mesa0 and libgl1-mesa-dri "
        "(make render-deps) or libosmesa6"
    )


def _require_offscreen_context() -> None:
    import mujoco.gl_context

    # mujoco picks the context class at import; with MUJOCO_GL=disable it defines none.
    context = getattr(mujoco.gl_context, "GLContext", None)
    backend = getattr(context, "__module__", "").rpartition(".")[2]
    if backend not in OFFSCREEN_BACKENDS:
        raise RenderingError(
            f"MuJoCo's OpenGL backend is {backend or 'disabled'!r}, not one of {sorted(OFFSCREEN_BACKENDS)}: set "
            "MUJOCO_GL (see carp.data.rendering.offscreen_backend) before mujoco is first imported"
        )


class CameraRenderer:
    """Renders a model's cameras from flattened simulator states; one OpenGL context, reused for every frame.

    The renderer holds the model by reference (it must outlive the renderer) and leaves it unchanged. Close it (or
    use it as a context manager) to free the OpenGL context while the library is still loaded.
    """

    def __init__(self, model, settings: RenderSettings) -> None:
        """Create the context for ``model`` (a ``mujoco.MjModel``).

        Raises:
            RenderingError: MuJoCo has no offscreen backend, or a camera is not in the model.
        """
        import mujoco

        _require_offscreen_context()
        cameras = [model.camera(index).name for index in range(model.ncam)]
        missing = [camera for camera in settings.cameras if camera not in cameras]
        if missing:
            raise RenderingError(f"cameras {missing} are not in the model (it has {cameras})")
        self.settings = settings
        self._model = model
        self._data = mujoco.MjData(model)
        # The sample count is read once, when the OpenGL context is made; the model is left as it was.
        samples = model.vis.quality.offsamples
        if not settings.anti_aliasing:
            model.vis.quality.offsamples = 0
        try:
            self._renderer = mujoco.Renderer(model, settings.image_size, settings.image_size)
        finally:
            model.vis.quality.offsamples = samples
        self._options = mujoco.MjvOption()
        self._options.geomgroup[COLLISION_GEOM_GROUP] = 0
        self._options.geomgroup[VISUAL_GEOM_GROUP] = 1
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = settings.shadows
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = settings.reflections
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = settings.skybox

    def render(self, state: np.ndarray) -> dict[str, np.ndarray]:
        """Images of every camera in one simulator state.

        Args:
            state: (1 + nq + nv,) robosuite's flattened state ``[time, qpos, qvel]`` (``sim.get_state().flatten()``).

        Returns:
            obs key ``<camera>_image`` -> (image_size, image_size, 3) uint8 upright RGB image.

        Raises:
            RenderingError: the state does not fit the model.
        """
        import mujoco

        model, data = self._model, self._data
        state = np.asarray(state, dtype=np.float64)
        expected = 1 + model.nq + model.nv
        if state.shape != (expected,):
            raise RenderingError(
                f"state shape={state.shape}: expected ({expected},) = 1 + nq {model.nq} + nv {model.nv} "
                "(time, qpos, qvel) for this model"
            )
        data.time = state[0]
        data.qpos[:] = state[1 : 1 + model.nq]
        data.qvel[:] = state[1 + model.nq :]
        mujoco.mj_forward(model, data)
        images = {}
        for camera, key in zip(self.settings.cameras, self.settings.image_keys, strict=True):
            self._renderer.update_scene(data, camera, self._options)
            images[key] = self._renderer.render().copy()  # the renderer reuses its output buffer
        return images

    def close(self) -> None:
        """Free the OpenGL context (idempotent)."""
        self._renderer.close()

    def __enter__(self) -> "CameraRenderer":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def load_demo_model(env, attrs: Mapping):
    """Put ``env`` in the MuJoCo model a demo was recorded in and return it (a ``mujoco.MjModel``).

    robosuite rebuilds its model at every reset with random object sizes and placements, so stored states are only
    meaningful in their own model. A robomimic file stores that model's XML per demo (attribute ``model_file``; its
    asset paths are rebased on this robosuite install as robomimic does); carp's collection stores the reset seed
    instead (attribute ``seed``), from which :func:`carp.tasks.arms.simulation.reset_env` rebuilds the same model.
    The seed gives the recorded model exactly; an XML holds its numbers to fewer digits, so poses differ by a rounding
    error and a few pixels on edges and fine textures may differ by some intensity levels.

    Args:
        env: a robosuite env built from the demo file's ``env_args``.
        attrs: the demo group's attributes.

    Raises:
        RenderingError: the demo has neither attribute.
    """
    from carp.tasks.arms.simulation import reset_env

    if "model_file" in attrs:
        env.reset()
        env.reset_from_xml_string(env.edit_model_xml(str(attrs["model_file"])))
    elif "seed" in attrs:
        reset_env(env, int(attrs["seed"]))
    else:
        raise RenderingError("the demo has neither a 'model_file' nor a 'seed' attribute: its model is unknown")
    return env.sim.model._model


def render_states(env, attrs: Mapping, states: np.ndarray, settings: RenderSettings) -> dict[str, np.ndarray]:
    """Render every stored state of one demo.

    Args:
        env: a robosuite env built from the demo file's ``env_args`` (no renderer of its own needed).
        attrs: the demo's attributes (``model_file`` or ``seed``, see :func:`load_demo_model`).
        states: (T, 1 + nq + nv) flattened states, one per observation step.
        settings: cameras, size and render flags.

    Returns:
        obs key ``<camera>_image`` -> (T, image_size, image_size, 3) uint8 upright RGB images.
    """
    model = load_demo_model(env, attrs)
    size = settings.image_size
    images = {key: np.empty((len(states), size, size, 3), dtype=np.uint8) for key in settings.image_keys}
    with CameraRenderer(model, settings) as renderer:
        for step, state in enumerate(states):
            for key, image in renderer.render(state).items():
                images[key][step] = image
    return images
