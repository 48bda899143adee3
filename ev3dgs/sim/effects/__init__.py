"""Optional sensor effects, one small module each. None of them runs unless its config table is present."""
