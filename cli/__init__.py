"""The `warpbags` command line (installed as `warpbags.cli`)."""
