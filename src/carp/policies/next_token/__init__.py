"""Next-token autoregressive baseline: CARP's tokens and transformer, one token per step with a kv-cache.

Modules: `config` (the family's frozen config), `transformer` (the model, teacher-forced and incremental),
`generation` (token-by-token inference and the check that a tokenizer fits the transformer).
"""
