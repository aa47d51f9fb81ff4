"""Token-by-token inference of the next-token transformer: L steps with a kv-cache (the policy decodes the ids).

Each step scores one token, chooses it (argmax, or a draw among the top k with CARP's Gumbel-max helpers from
`carp.policies.carp.sampling`, the chunk's uniforms drawn up front) and feeds it back. The condition, the AdaLN
modulations and the position embeddings are computed once per chunk by `start_inference`.
"""

import torch

from carp.policies.carp.sampling import check_top_k, sampling_uniforms, select_tokens
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.wrapper import check_tokenizer_fit
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


@torch.inference_mode()
def generate_tokens(
    transformer: NextTokenTransformer,
    obs_features: torch.Tensor,
    top_k: int = 1,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Predict the L token ids of one chunk per observation, one token per transformer call.

    Args:
        transformer: the trained transformer, in eval mode.
        obs_features: (B, To, F) observation features.
        top_k: 1 takes the argmax; k > 1 draws among the k most likely tokens.
        generator: random source of the draws (seeded for reproducible chunks); unused for top_k = 1.

    Returns:
        (B, L) long token ids in CARP's sequence order.
    """
    check_top_k(top_k, transformer.codebook_size)
    batch, length = obs_features.shape[0], transformer.sequence_length
    uniforms = (
        sampling_uniforms(batch, length, top_k, generator, obs_features.device) if top_k > 1 else None
    )  # (B, L, k)
    state = transformer.start_inference(obs_features)
    token_ids = torch.empty(batch, length, dtype=torch.long, device=obs_features.device)
    previous = None
    for position in range(length):
        logits = transformer.next_token_logits(state, previous)  # (B, V)
        if uniforms is None:
            previous = logits.max(dim=-1).indices  # (B,)
        else:
            previous = select_tokens(logits.unsqueeze(1), top_k, uniforms=uniforms[:, position : position + 1])[:, 0]
        token_ids[:, position] = previous
    return token_ids


def check_tokenizer_matches(transformer: NextTokenTransformer, tokenizer: MultiScaleActionTokenizer) -> None:
    """Raise ValueError unless the transformer was sized for this tokenizer's ids (A, scales, V)."""
    spec = tokenizer.spec
    pairs = {
        "action_dim": (transformer.action_dim, spec.action_dim),
        "scales": (transformer.layout.scales, tuple(spec.scales)),
        "codebook_size": (transformer.codebook_size, spec.codebook_size),
    }
    check_tokenizer_fit(pairs, "model", "next-token transformer does not match the tokenizer")
