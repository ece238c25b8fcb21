"""`rotate finetune-adapter`: its config, the shared core, and its three paths (simulation, recorded sessions,
head refit)."""
