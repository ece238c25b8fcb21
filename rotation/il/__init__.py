"""Imitation learning from demonstrations (`rotate train-il`): the touch benchmarks' policies, plug insertion first."""
