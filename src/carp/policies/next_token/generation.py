"""Token-by-token inference of the next-token transformer: L steps with a kv-cache (the policy decodes the ids).

`generate_tokens` predicts carp_msvq's L ids; `generate_sequences` the tokens of another kind, up to L (or a
variable-length kind's maximum) and stopping at the end token.

Each step scores one token, chooses it (argmax, or a draw among the top k with CARP's Gumbel-max helpers from
`carp.policies.carp.sampling`, the chunk's uniforms drawn up front) and feeds it back. The condition, the AdaLN
modulations and the position embeddings are computed once per chunk by `start_inference`.
"""

import torch

from carp.policies.carp.sampling import check_top_k, sampling_uniforms, select_tokens
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.wrapper import check_tokenizer_fit
from carp.tokenizer.kinds.base import PADDING_ID, TokenBatch
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


@torch.inference_mode()
def generate_sequences(
    transformer: NextTokenTransformer,
    obs_features: torch.Tensor,
    steps: int,
    end_id: int | None = None,
    top_k: int = 1,
    generator: torch.Generator | None = None,
) -> TokenBatch:
    """Predict a token sequence per observation, one token per call, up to `steps` tokens or the end token.

    The token choice is :func:`generate_tokens`'s (the end token competes with the others); a row ends at its first
    end token, which is not part of its tokens, and generation stops once every row has ended.

    Args:
        transformer: the trained transformer of a shared vocabulary (`action_dim` 1), in eval mode.
        obs_features: (B, To, F) observation features.
        steps: the most tokens a row takes (`L`, or a variable-length kind's maximum).
        end_id: id of the end token; None for a fixed-length kind, whose rows are all `steps` long.
        top_k: 1 takes the argmax; k > 1 draws among the k most likely tokens.
        generator: random source of the draws; unused for top_k = 1.

    Returns:
        ids (B, steps) long, :data:`~carp.tokenizer.kinds.base.PADDING_ID` past each row's end, and the lengths (B,).
    """
    check_top_k(top_k, transformer.codebook_size)
    batch, device = obs_features.shape[0], obs_features.device
    uniforms = sampling_uniforms(batch, steps, top_k, generator, device) if top_k > 1 else None  # (B, steps, k)
    state = transformer.start_inference(obs_features)
    token_ids = torch.full((batch, steps), PADDING_ID, dtype=torch.long, device=device)
    lengths = torch.full((batch,), steps, dtype=torch.long, device=device)
    ended = torch.zeros(batch, dtype=torch.bool, device=device)
    previous = None
    for position in range(steps):
        logits = transformer.next_token_logits(state, previous)  # (B, V)
        if uniforms is None:
            chosen = logits.max(dim=-1).indices  # (B,)
        else:
            chosen = select_tokens(logits.unsqueeze(1), top_k, uniforms=uniforms[:, position : position + 1])[:, 0]
        if end_id is not None:
            stopping = (chosen == end_id) & ~ended
            lengths[stopping] = position
            ended |= stopping
            if bool(ended.all()):
                break
        token_ids[:, position] = torch.where(ended, PADDING_ID, chosen)
        # An ended row's input no longer matters (its later logits are ignored); the end token is a valid one.
        previous = chosen if end_id is None else torch.where(ended, end_id, chosen)
    return TokenBatch(token_ids.cpu(), lengths.cpu())


def check_tokenizer_matches(transformer: NextTokenTransformer, tokenizer: MultiScaleActionTokenizer) -> None:
    """Raise ValueError unless the transformer was sized for this tokenizer's ids (A, scales, V)."""
    spec = tokenizer.spec
    pairs = {
        "action_dim": (transformer.action_dim, spec.action_dim),
        "scales": (transformer.layout.scales, tuple(spec.scales)),
        "codebook_size": (transformer.codebook_size, spec.codebook_size),
    }
    check_tokenizer_fit(pairs, "model", "next-token transformer does not match the tokenizer")
