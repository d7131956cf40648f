"""Typed presets and scene definitions (installed as `warpbags.configs`)."""
