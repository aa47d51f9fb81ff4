"""Coarse-to-fine inference: K next-scale steps with a kv-cache, then decoding.

The procedure is summarized in docs/architecture.md, "Next-scale inference".

Mirrors `autoregressive_infer_cfg` of VAR and the official CARP without classifier-free guidance. Per scale the
transformer scores all `s_k * A` tokens at once, a token is chosen per position (argmax, or a draw from the top-k
with a seedable generator), the tokenizer adds that scale's contribution to f_hat for all dimensions at once, and
f_hat area-downsampled to the next scale becomes the next input.

Top-k draws use the Gumbel-max trick: with u uniform in (0, 1), argmax over the k largest logits of
``logit - log(-log(u))`` is a draw from the softmax over those k logits. The uniforms of a whole chunk, (B, L, k), are
drawn up front from the generator (:func:`sampling_uniforms`), so the exported ONNX graph
(`carp.policies.carp.onnx_policy`), which takes them as an input, chooses the same tokens as this module.
"""

from dataclasses import dataclass

import torch

from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


@dataclass
class GeneratedChunk:
    """Result of coarse-to-fine prediction, before decoding.

    Attributes:
        token_ids: K tensors (B, A, s_k) long, the chosen tokens per scale in the tokenizer's layout.
        latent: (B, A, C, l) f_hat accumulated over all scales.
    """

    token_ids: list[torch.Tensor]
    latent: torch.Tensor


def check_top_k(top_k: int, vocabulary: int) -> None:
    """Refuse a `top_k` that is not an integer in [1, V]."""
    if isinstance(top_k, bool) or not isinstance(top_k, int) or not 1 <= top_k <= vocabulary:
        raise ValueError(f"top_k must be an integer in [1, V = {vocabulary}], got {top_k!r}")


def sampling_uniforms(
    batch_size: int,
    sequence_length: int,
    top_k: int,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The uniforms (B, L, k) float32 that one chunk's top-k draws consume, from `generator` (on `device`)."""
    return torch.rand(batch_size, sequence_length, top_k, generator=generator, device=device)


def gumbel_top_k(logits: torch.Tensor, uniforms: torch.Tensor) -> torch.Tensor:
    """Draw one token per position from the softmax over its k largest logits.

    Args:
        logits: (B, N, V) float.
        uniforms: (B, N, k) float in [0, 1), one per candidate; k = uniforms.shape[-1].

    Returns:
        (B, N) long token ids, each among its position's k largest logits.
    """
    top_logits, top_ids = logits.topk(uniforms.shape[-1], dim=-1)  # (B, N, k)
    # Clamped away from 0 and 1 so that both logarithms stay finite.
    tiny = torch.finfo(uniforms.dtype).tiny
    gumbel = -torch.log(-torch.log(uniforms.clamp(tiny, 1.0 - 1e-7)))  # (B, N, k)
    choice = (top_logits + gumbel.to(top_logits.dtype)).argmax(dim=-1, keepdim=True)  # (B, N, 1)
    return top_ids.gather(-1, choice).squeeze(-1)  # (B, N)


def select_tokens(
    logits: torch.Tensor,
    top_k: int = 1,
    generator: torch.Generator | None = None,
    uniforms: torch.Tensor | None = None,
) -> torch.Tensor:
    """Choose one token per position.

    Args:
        logits: (B, N, V) float.
        top_k: 1 takes the argmax (deterministic); k > 1 samples from the softmax over the k largest logits.
        generator: random source for sampling (pass a seeded one for reproducible draws); ignored for top_k = 1.
        uniforms: (B, N, k) pre-drawn uniforms to sample with instead of drawing from `generator`.

    Returns:
        (B, N) long token ids.
    """
    check_top_k(top_k, logits.shape[-1])
    if top_k == 1:
        # max().indices is faster than argmax() on the CPU for (B, N, V) logits, with the same result.
        return logits.max(dim=-1).indices  # (B, N)
    if uniforms is None:
        uniforms = sampling_uniforms(*logits.shape[:-1], top_k, generator, logits.device)
    if tuple(uniforms.shape) != (*logits.shape[:-1], top_k):
        raise ValueError(f"uniforms must have shape {(*logits.shape[:-1], top_k)}, got {tuple(uniforms.shape)}")
    return gumbel_top_k(logits, uniforms)


def generate_chunk(
    transformer: CoarseToFineTransformer,
    tokenizer: MultiScaleActionTokenizer,
    obs_features: torch.Tensor,
    top_k: int = 1,
    generator: torch.Generator | None = None,
) -> GeneratedChunk:
    """Predict the tokens of all K scales for a batch of observations.

    Call under `torch.inference_mode()`; the caller owns the mode so the policy can time prediction and decoding
    separately.

    Args:
        transformer: the coarse-to-fine transformer, in eval mode.
        tokenizer: the frozen tokenizer whose codebooks the transformer was trained on.
        obs_features: (B, To, F) observation features (`CarpPolicy.observation_features`).
        top_k: see :func:`select_tokens`.
        generator: see :func:`select_tokens`.

    Returns:
        The chosen token ids and f_hat (B, A, C, l).
    """
    layout = transformer.layout
    check_top_k(top_k, transformer.spec.codebook_size)
    uniforms = (
        sampling_uniforms(obs_features.shape[0], layout.sequence_length, top_k, generator, obs_features.device)
        if top_k > 1
        else None
    )  # (B, L, k)
    state = transformer.start_inference(obs_features)
    latent = tokenizer.empty_latent(obs_features.shape[0], device=obs_features.device)  # (B, A, C, l)
    scale_inputs = None
    token_ids = []
    for scale_index, (start, end) in enumerate(layout.scale_bounds):
        logits = transformer.next_scale_logits(state, scale_inputs)  # (B, s_k * A, V)
        scale_uniforms = None if uniforms is None else uniforms[:, start:end]  # (B, s_k * A, k)
        scale_ids = layout.scale_tokens_to_ids(select_tokens(logits, top_k, uniforms=scale_uniforms))  # (B, A, s_k)
        token_ids.append(scale_ids)
        latent = tokenizer.embed_scale(latent, scale_ids, scale_index)  # (B, A, C, l)
        if scale_index + 1 < layout.num_scales:
            next_input = tokenizer.next_scale_input(latent, scale_index)  # (B, A, C, s_{k+1})
            scale_inputs = layout.scale_inputs_to_tokens(next_input)  # (B, s_{k+1} * A, C)
    return GeneratedChunk(token_ids, latent)
