"""Policy families behind one seam (docs/architecture.md, "Policy families").

- `base`: the `Policy` protocol every family implements, `TimedPrediction`, `Deployment`, the checkpoint format
  version.
- `context`: `PolicyContext`, what a family is sized by besides its own params section (shapes, normalizers,
  tokenizer).
- `wrapper`: `PolicyModule` and `TokenizedPolicy`, the family-independent parts of the PyTorch policies.
- `registry`: family name -> `PolicyFamily` (config class, builder, loader), one line per family, and `load_policy`,
  which dispatches on the `policy_type` stored in every checkpoint.
- One folder per family: `carp/` (coarse-to-fine autoregressive), `diffusion/` (Diffusion Policy U-Net and
  transformer), `next_token/` (next-token autoregressive baseline), `vq_bet/` (VQ-BeT baseline), `consistency/`
  (Consistency Policy: the EDM teacher `edm_unet` and the distilled student `consistency_policy`). Nothing outside
  a family's folder names its classes.
"""
