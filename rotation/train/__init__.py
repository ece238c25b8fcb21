"""Training: teacher PPO on the batched env, student distillation."""
