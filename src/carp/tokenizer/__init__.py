"""Multi-scale residual action tokenizer: one VQ-VAE per action dimension, vectorized over dimensions."""

from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer, TokenizerOutput

__all__ = ["MultiScaleActionTokenizer", "TokenizerOutput", "TokenizerSpec"]
