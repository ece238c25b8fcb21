"""`rotate pretrain`: self-distillation of a touch encoder (config, objectives, saved state, logs, the job)."""
