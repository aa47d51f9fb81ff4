"""Coarse-to-fine autoregressive policy.

Overview in docs/architecture.md, "Token layout and attention mask" and "Coarse-to-fine transformer".

- `spec`: `PolicySpec`, the shapes of data and tokenizer with CARP's params section, which size the transformer.
- `layout`: token order of a chunk, level ids and the block-causal mask.
- `blocks`: attention with a kv-cache, the AdaLN block, the per-dimension head.
- `transformer`: `CoarseToFineTransformer`, teacher-forced forward and K-step inference, on `AdaptiveTransformer`
  (the AdaLN trunk the next-token family shares).
- `sampling`: greedy / top-k token choice and the coarse-to-fine generation loop.
- `policy`: `CarpPolicy`, normalizers + frozen tokenizer + transformer, with `predict_action` and checkpoints.
- `onnx_policy`: the batch-1 ONNX Runtime graphs evaluation runs (`CarpPolicy.deployment`).
- `trainer`: CARP's part of the shared training loop: token targets computed once, the teacher-forced step with its
  token accuracies, the optimizer recipe.
- `family`: CARP's entry in `carp.policies.registry`.
"""
