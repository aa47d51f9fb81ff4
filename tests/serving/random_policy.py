"""A randomly initialized CARP policy for Lift that records its serving protocol (a test factory, not the library).

What the serving tests, the example control loop (`examples/serve_control_loop.py`) and the latency benchmark
(`benchmarks/serving_latency.py`) serve without a trained checkpoint; those two put the repository root on the path.

Its actions are meaningless (random weights) but well formed: 10-D absolute actions (`panda-abs10`) inside a box
around Lift's workspace, so a simulator can execute them. Its speed does not depend on the weights.
"""

import numpy as np
import torch

from carp.config import DataConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.serving.protocol import SERVING_METADATA_KEY, training_protocol
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

LIFT_OBS_WIDTHS = {"object": 10, "robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}
"""Lift's default low-dim observation keys (`carp.tasks`' `default_obs_keys`) and their widths, Do = 19."""

ACTION_SPACE = "panda-abs10"
ACTION_MINIMUM = np.array([-0.25, -0.25, 0.8, -1, -1, -1, -1, -1, -1, -1], dtype=np.float64)
ACTION_MAXIMUM = np.array([0.25, 0.25, 1.1, 1, 1, 1, 1, 1, 1, 1], dtype=np.float64)
"""A box around the table top for the position, every 6-D rotation, and both gripper commands."""


def random_lift_policy(tiny: bool = True, obs_steps: int = 2, action_steps: int | None = None, seed: int = 0):
    """A CARP policy with random weights for Lift's default observation, with task and protocol in its metadata.

    Args:
        tiny: H = 8, scales (1, 2), V = 8, depth 1, D = 16 (tests); otherwise the default configuration (H = 16,
            scales (1, 2, 3, 4), V = 512, `CarpConfig`'s defaults), whose speed is the one that matters.
        obs_steps: `To`.
        action_steps: `Ta`; None for `H / 2`, as the params' defaults have it.
        seed: seeds the weights.

    Returns:
        A `CarpPolicy` in eval mode.
    """
    torch.manual_seed(seed)
    if tiny:
        tokenizer_spec = TokenizerSpec(
            action_dim=10, action_horizon=8, scales=(1, 2), codebook_size=8, latent_channels=4
        )
        config = CarpConfig(depth=1, width=16, num_heads=2)
    else:
        tokenizer_spec, config = TokenizerSpec(action_dim=10), CarpConfig()
    horizon = tokenizer_spec.action_horizon
    obs_dim = sum(LIFT_OBS_WIDTHS.values())
    spec = PolicySpec(
        obs_dim=obs_dim,
        obs_steps=obs_steps,
        action_dim=tokenizer_spec.action_dim,
        scales=tokenizer_spec.scales,
        latent_channels=tokenizer_spec.latent_channels,
        codebook_size=tokenizer_spec.codebook_size,
        config=config,
    )
    action_normalizer = MinMaxNormalizer(ACTION_MINIMUM, ACTION_MAXIMUM)
    tokenizer = MultiScaleActionTokenizer(tokenizer_spec).eval()
    data = DataConfig(
        obs_steps=obs_steps,
        action_horizon=horizon,
        action_steps=action_steps if action_steps is not None else horizon // 2,
    )
    attrs = {"obs_keys": list(LIFT_OBS_WIDTHS), "obs_widths": list(LIFT_OBS_WIDTHS.values())}
    return CarpPolicy(
        TokenizerArtifact.build(tokenizer, {"lift": action_normalizer}, ACTION_SPACE),
        CoarseToFineTransformer(spec).eval(),
        MinMaxNormalizer(np.full(obs_dim, -1.0), np.full(obs_dim, 1.0)),
        action_normalizer,
        metadata={"task": "lift", SERVING_METADATA_KEY: training_protocol(data, attrs)},
    )
