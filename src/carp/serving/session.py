"""What a served policy expects, and one connection's episode: its observation history and its random draws.

A robot sends one step's observation per request; the server keeps the last ``To`` steps, as the rollout loop does
(`carp.evaluation.rollout.run_episode`): at the start of an episode the first observation fills the whole history,
afterwards each new one pushes out the oldest. Sampling draws come from a CPU generator seeded per episode, as
`carp.evaluation.sources.PolicySource.reset` seeds it, so a served chunk equals the chunk an in-process rollout
with the same observations and seed predicts.

A request is a map:

- ``obs``: (Do,) float32, the low-dim observation features of the current step (the spec's `obs_keys`
  concatenated in this order); or, when the spec knows each key's width (a checkpoint that records its protocol,
  `carp.serving.protocol`), one (width,) float32 array per key under the key's own name, e.g.
  ``{"object": (10,), "robot0_eef_pos": (3,), ...}``, which the server concatenates in the spec's order. A request
  sends one form or the other, not both.
- ``images``: (cameras, 3, h, w) uint8 camera images of the current step; only for an image policy.
- ``predict`` (optional bool, default true): false only adds the observation to the history and gets a reply
  without ``actions``. A robot that executes ``Ta`` actions per chunk sends the steps in between this way, so that
  the history holds the last ``To`` steps when it asks for the next chunk, as in the rollout loop.
- ``reset`` (optional bool): this observation starts a new episode; ``seed`` (optional int, default 0) seeds its
  draws. A new connection starts an episode with seed 0.
- ``step`` and ``timestamp`` (optional): echoed in the reply, so the robot can match replies and measure latency.

Other keys are ignored (an openpi client may send its own).
"""

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

OBS_KEY = "obs"
IMAGES_KEY = "images"


class RequestError(ValueError):
    """A request the policy cannot answer; the message is one line that starts with the offending key."""


@dataclass(frozen=True)
class ServingSpec:
    """The contract between a served policy and its robots (symbols as in docs/architecture.md, "Symbols").

    Attributes:
        obs_keys: names of the low-dim observation keys concatenated, in this order, into the `Do` features of
            ``obs``.
        obs_steps: `To`, observation steps the policy conditions on.
        obs_dim: `Do`, low-dim observation features per step.
        action_horizon: `H`, actions per predicted chunk.
        action_dim: `A`, action dimensions.
        action_steps: `Ta`, actions of a chunk the robot executes, from row `To - 1` on
            (`carp.evaluation.sources.executed_actions`).
        control_period_s: seconds between two control steps (1 / the task's control frequency).
        image_shape: (cameras, 3, h, w) of one step's camera images for an image policy; None for a state policy.
        obs_widths: features of each of `obs_keys`, summing to `Do`; None when unknown (a spec derived from params
            for a checkpoint that does not record its protocol), in which case requests must send ``obs``.
        cameras: names of the cameras of ``images``, in order; empty when unknown or for a state policy.
    """

    obs_keys: tuple[str, ...]
    obs_steps: int
    obs_dim: int
    action_horizon: int
    action_dim: int
    action_steps: int
    control_period_s: float
    image_shape: tuple[int, ...] | None = None
    obs_widths: tuple[int, ...] | None = None
    cameras: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "obs_keys", tuple(self.obs_keys))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        if self.obs_widths is not None:
            object.__setattr__(self, "obs_widths", tuple(self.obs_widths))
            if len(self.obs_widths) != len(self.obs_keys) or sum(self.obs_widths) != self.obs_dim:
                raise ValueError(
                    f"ServingSpec: obs_widths {list(self.obs_widths)} of keys {list(self.obs_keys)} do not add up to "
                    f"Do = {self.obs_dim}"
                )
            if {OBS_KEY, IMAGES_KEY} & set(self.obs_keys):
                raise ValueError(f"ServingSpec: an observation key may not be named {OBS_KEY} or {IMAGES_KEY}")
        if self.image_shape is not None:
            object.__setattr__(self, "image_shape", tuple(self.image_shape))
        for name in ("obs_steps", "obs_dim", "action_horizon", "action_dim", "action_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ServingSpec.{name} must be a positive integer, got {value!r}")
        if self.obs_steps - 1 + self.action_steps > self.action_horizon:
            raise ValueError(
                f"ServingSpec: To - 1 + Ta = {self.obs_steps - 1 + self.action_steps} exceeds H = {self.action_horizon}"
            )
        if not self.control_period_s > 0:
            raise ValueError(f"ServingSpec.control_period_s must be positive, got {self.control_period_s!r}")
        if self.image_shape is not None and (len(self.image_shape) != 4 or self.image_shape[1] != 3):
            raise ValueError(f"ServingSpec.image_shape must be (cameras, 3, h, w), got {self.image_shape}")

    @property
    def executed_offset(self) -> int:
        """Row of a chunk that acts at the request's step: `To - 1`."""
        return self.obs_steps - 1

    def observation_spec(self) -> dict[str, dict[str, Any]]:
        """Per request key: its shape, dtype and meaning, as the metadata frame lists them."""
        spec: dict[str, dict[str, Any]] = {
            OBS_KEY: {"shape": [self.obs_dim], "dtype": "float32", "keys": list(self.obs_keys)},
        }
        if self.obs_widths is not None:
            spec[OBS_KEY]["widths"] = list(self.obs_widths)
        if self.image_shape is not None:
            spec[IMAGES_KEY] = {"shape": list(self.image_shape), "dtype": "uint8", "layout": "cameras, 3, h, w"}
            if self.cameras:
                spec[IMAGES_KEY]["cameras"] = list(self.cameras)
        return spec

    def key_spec(self) -> dict[str, dict[str, Any]]:
        """Per low-dim observation key, in order: its shape and dtype; empty when the widths are unknown."""
        if self.obs_widths is None:
            return {}
        return {key: {"shape": [width], "dtype": "float32"} for key, width in zip(self.obs_keys, self.obs_widths)}


def _array(request: Mapping[str, Any], key: str, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    if key not in request:
        raise RequestError(f"{key}: missing")
    value = request[key]
    if not isinstance(value, np.ndarray):
        raise RequestError(f"{key}: expected a {dtype} array of shape {shape}, got {type(value).__name__}")
    if value.shape != shape:
        raise RequestError(f"{key}: expected shape {shape}, got {value.shape}")
    if value.dtype != dtype:
        raise RequestError(f"{key}: expected dtype {dtype}, got {value.dtype}")
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        raise RequestError(f"{key}: holds NaN or infinite values")
    return value


def _optional_number(request: Mapping[str, Any], key: str, default: Any, types: tuple[type, ...]) -> Any:
    if key not in request:
        return default
    value = request[key]
    if isinstance(value, bool) or not isinstance(value, types):
        raise RequestError(f"{key}: expected {'an integer' if types == (int,) else 'a number'}, got {value!r}")
    return value


@dataclass(frozen=True)
class Observed:
    """The inputs of one prediction, copies the session no longer writes to.

    Attributes:
        obs_history: (To, Do) float32 raw observations, oldest first.
        image_history: (To, cameras, 3, h, w) uint8, or None for a state policy.
        generator: the episode's random source; used by one prediction at a time (a connection's requests are
            answered in order).
        echo: the request's ``step`` and ``timestamp`` (None where it sent none), for the reply.
        predict: whether the request asks for a chunk (false: observation only).
    """

    obs_history: np.ndarray
    image_history: np.ndarray | None
    generator: torch.Generator
    echo: dict[str, Any] = field(default_factory=dict)
    predict: bool = True


class Session:
    """One connection's episode: validates each request against the spec and keeps the last `To` observations."""

    def __init__(self, spec: ServingSpec) -> None:
        self.spec = spec
        self.generator = torch.Generator()
        self._history: deque[np.ndarray] = deque(maxlen=spec.obs_steps)
        self._images: deque[np.ndarray] = deque(maxlen=spec.obs_steps)
        self.reset(seed=0)

    def reset(self, seed: int) -> None:
        """Start a new episode whose draws come from `seed`; the next observation fills the history."""
        self.generator.manual_seed(seed)
        self._history.clear()
        self._images.clear()

    def _observation(self, request: Mapping[str, Any]) -> np.ndarray:
        """(Do,) float32 features of `request`: its ``obs``, or its per-key arrays concatenated in the spec's order."""
        spec, float32 = self.spec, np.dtype(np.float32)
        sent_keys = [key for key in spec.obs_keys if key in request] if spec.obs_widths is not None else []
        if OBS_KEY in request:
            if sent_keys:
                raise RequestError(f"{sent_keys[0]}: send either obs or the per-key observations, not both")
            return _array(request, OBS_KEY, (spec.obs_dim,), float32)
        if not sent_keys:
            per_key = f" or each of {', '.join(spec.obs_keys)}" if spec.obs_widths is not None else ""
            raise RequestError(f"{OBS_KEY}: missing (send obs ({spec.obs_dim},) float32{per_key})")
        parts = [_array(request, key, (width,), float32) for key, width in zip(spec.obs_keys, spec.obs_widths)]
        return np.concatenate(parts)  # (Do,)

    def observe(self, request: Mapping[str, Any]) -> Observed:
        """Validate `request` (see the module docstring), then add its observation to the history.

        A request that fails validation leaves the session as it was.

        Raises:
            RequestError: a missing key (``obs``, or one of the per-key observations), both forms at once, a wrong
                shape or dtype, a non-finite value, a malformed `predict`, `reset`, `seed`, `step` or `timestamp`.
        """
        if not isinstance(request, Mapping):
            raise RequestError(f"request: expected a map, got {type(request).__name__}")
        obs = self._observation(request)
        images = None
        if self.spec.image_shape is not None:
            images = _array(request, IMAGES_KEY, self.spec.image_shape, np.dtype(np.uint8))
        reset, predict = request.get("reset", False), request.get("predict", True)
        for key, flag in (("reset", reset), ("predict", predict)):
            if not isinstance(flag, bool):
                raise RequestError(f"{key}: expected true or false, got {type(flag).__name__}")
        seed = _optional_number(request, "seed", 0, (int,))
        echo = {
            "step": _optional_number(request, "step", None, (int,)),
            "timestamp": _optional_number(request, "timestamp", None, (int, float)),
        }
        if reset:
            self.reset(seed)
        if not self._history:
            # The rollout loop's padding: the first observation stands in for the steps before the episode.
            self._history.extend([obs.copy()] * self.spec.obs_steps)
            if images is not None:
                self._images.extend([images.copy()] * self.spec.obs_steps)
        else:
            self._history.append(obs.copy())
            if images is not None:
                self._images.append(images.copy())
        return Observed(
            obs_history=np.stack(self._history),  # (To, Do)
            image_history=np.stack(self._images) if images is not None else None,  # (To, cameras, 3, h, w)
            generator=self.generator,
            echo=echo,
            predict=predict,
        )
