"""VQ-BeT baseline (Lee et al. 2024): a residual VQ-VAE over action chunks and a GPT that predicts its codes.

Modules: `config` (the family's frozen configs), `quantizer` (the residual vector quantizer with EMA codebooks),
`autoencoder` (the MLP VQ-VAE over chunks and its training), `losses` (focal loss), `transformer` (the GPT with its
code and offset heads), `policy` (the deployable policy), `family` (the registry entry and the two-phase training).
"""
