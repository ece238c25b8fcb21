"""Job modules behind the `rotate` subcommands (one per workflow step)."""
