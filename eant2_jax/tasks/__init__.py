"""Tasks: what a network is scored on."""
