"""The next-token network over another tokenizer kind, widened to the size it has over carp_msvq's tokens.

A kind sets the vocabulary of the embedding and the head and the length of the position table. carp_msvq keeps one
vocabulary per action dimension (A x V embedding rows and a head per dimension), so at one width the network over
another kind's single vocabulary has about half as many trained parameters, and a comparison of kinds under the
next-token policy would also be a comparison of network sizes. With `next_token.match_size` the family chooses the
width, a multiple of `num_heads`, whose transformer's trained parameters are nearest those of the transformer the
same section builds over carp_msvq's tokens (the params' scales and codebook size); depth, heads and the feed-forward
ratio stay the section's. Trained parameters grow with the width, so the nearest width is found by bisection.
"""

import dataclasses
from collections.abc import Callable

import torch

from carp.policies.base import count_parameters
from carp.policies.context import MsvqLayout
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.transformer import NextTokenTransformer

TransformerBuilder = Callable[[NextTokenConfig], NextTokenTransformer]
"""Builds the transformer of one kind at the width of the config it is given."""


def msvq_parameters(config: NextTokenConfig, obs_dim: int, obs_steps: int, action_dim: int, layout: MsvqLayout) -> int:
    """Trained parameters of the next-token transformer over carp_msvq's tokens at `config`'s width.

    Args:
        config: the section as set (its width is the reference width).
        obs_dim: `F`, observation features per step.
        obs_steps: `To`.
        action_dim: `A`, one carp_msvq vocabulary per dimension.
        layout: the params' carp_msvq scales and codebook size.
    """
    return _trained_parameters(
        lambda: NextTokenTransformer(config, obs_dim, obs_steps, action_dim, layout.scales, layout.codebook_size)
    )


def width_nearest(config: NextTokenConfig, target: int, build: TransformerBuilder) -> tuple[NextTokenConfig, int]:
    """`config` at the width (a multiple of `num_heads`) whose transformer has trained parameters nearest `target`.

    Args:
        config: the section; only its width changes.
        target: the trained parameters to match, >= 1.
        build: the kind's transformer at a given config.

    Returns:
        The config at the chosen width, and its transformer's trained parameters. Of two widths equally near, the
        narrower.
    """
    if target < 1:
        raise ValueError(f"the parameter target must be >= 1, got {target}")
    heads = config.num_heads

    def parameters(multiple: int) -> int:
        return _trained_parameters(lambda: build(dataclasses.replace(config, width=multiple * heads)))

    low, high = 1, 1
    while parameters(high) < target:
        low, high = high, 2 * high
    # parameters(low) < target <= parameters(high), unless high == 1
    while high - low > 1:
        middle = (low + high) // 2
        if parameters(middle) < target:
            low = middle
        else:
            high = middle
    below, above = parameters(low), parameters(high)
    multiple, counted = (low, below) if target - below <= above - target else (high, above)
    return dataclasses.replace(config, width=multiple * heads), counted


def _trained_parameters(build: Callable[[], torch.nn.Module]) -> int:
    """Trained parameters of the module `build` makes; the default random stream is left as it was."""
    # Sizing draws no weights of the policy: the policy built afterwards gets the initialization its seed gives.
    with torch.random.fork_rng(devices=[]):
        return count_parameters(build())
