"""tokenizer package of carp."""
