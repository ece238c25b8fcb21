"""Torch side of the stack: policies, training, touch encoders, data, hardware, deploy, evaluation."""
