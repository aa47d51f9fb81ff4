"""sweep package of carp."""
