"""Action tokenizer kinds behind one interface (`carp.tokenizer.kinds.base`) and one registry (`.registry`)."""
