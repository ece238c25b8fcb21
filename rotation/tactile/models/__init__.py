"""The touch encoders' networks: Sparsh-X and Sparsh-skin, their inputs, blocks, token interface, pooling and
the registry of encoders the jobs train or probe."""
