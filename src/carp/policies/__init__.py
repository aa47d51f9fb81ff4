"""Policy families: one folder per family, each with its config and model (STYLE.md "Families behind one seam")."""
