"""Consistency Policy (Prasad et al., RSS 2024): an EDM teacher on DP-C's U-Net and its distilled one-step student.

Modules: `config` (the `edm_unet` and `consistency_policy` sections and their inference sections), `karras` (EDM's
noise levels, preconditioning, Heun solver and loss weighting), `policy` (the teacher and student policies),
`distillation` (the consistency-trajectory and denoising losses, the target network, the warm start), `family` (the
two registry entries). The U-Net is `carp.policies.diffusion.unet`'s, with a second noise-level input for the
student.
"""
