"""Policy networks, observation normalization, the policy bundle and its export."""
