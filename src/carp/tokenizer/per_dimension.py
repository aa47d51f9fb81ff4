"""Convert between one vectorized tokenizer and A single-dimension tokenizers (action_dim = 1).

Every parameter of `MultiScaleActionTokenizer` is laid out dimension-major along axis 0: grouped conv weights
(A * out, in, 1, k), transposed-conv weights (A * in, out, 1, k), biases and GroupNorm affines (A * channels) and the
codebook (A, V, C). A single-dimension tokenizer has the same parameter names with A = 1, so merging is a
concatenation along axis 0 and splitting is the inverse. This is how the equivalence tests and the throughput
benchmark build matching "loop over A modules" baselines.
"""

from collections.abc import Sequence
from dataclasses import replace

import torch

from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


def single_dimension_spec(spec: TokenizerSpec) -> TokenizerSpec:
    """The same architecture for one action dimension."""
    return replace(spec, action_dim=1)


def merge_single_dimension_tokenizers(
    tokenizers: Sequence[MultiScaleActionTokenizer],
) -> MultiScaleActionTokenizer:
    """Build a vectorized tokenizer whose dimension d computes exactly what `tokenizers[d]` computes.

    Args:
        tokenizers: A tokenizers, each with action_dim = 1 and otherwise identical specs.

    Returns:
        A tokenizer with action_dim = A on the device of the inputs.
    """
    if not tokenizers:
        raise ValueError("need at least one single-dimension tokenizer to merge")
    base_spec = tokenizers[0].spec
    for tokenizer in tokenizers:
        if tokenizer.spec != single_dimension_spec(base_spec):
            raise ValueError(f"every tokenizer must share one spec with action_dim=1, got {tokenizer.spec}")
    merged = MultiScaleActionTokenizer(replace(base_spec, action_dim=len(tokenizers)))
    states = [tokenizer.state_dict() for tokenizer in tokenizers]
    merged_state = {name: torch.cat([state[name] for state in states], dim=0) for name in states[0]}
    merged.load_state_dict(merged_state, strict=True)
    return merged.to(next(tokenizers[0].parameters()).device)


def split_into_single_dimension_tokenizers(tokenizer: MultiScaleActionTokenizer) -> list[MultiScaleActionTokenizer]:
    """Inverse of `merge_single_dimension_tokenizers`: A independent tokenizers with action_dim = 1."""
    num_dimensions = tokenizer.spec.action_dim
    state = tokenizer.state_dict()
    device = next(tokenizer.parameters()).device
    singles = []
    for dimension in range(num_dimensions):
        single = MultiScaleActionTokenizer(single_dimension_spec(tokenizer.spec))
        single_state = {name: torch.chunk(value, num_dimensions, dim=0)[dimension] for name, value in state.items()}
        single.load_state_dict(single_state, strict=True)
        singles.append(single.to(device))
    return singles
