"""Diffusion Policy (Chi et al., RSS 2023): the 1-D temporal U-Net (DP-C) and the transformer denoiser (DP-T).

Modules: `config` (one frozen config per family), `unet`, `transformer`, `embedding` (diffusion-step embedding shared
by both), `sampler` (training noise and DDPM/DDIM inference through `diffusers`), `ema` (DP's EMA of weights on
torch's `AveragedModel`).
"""
