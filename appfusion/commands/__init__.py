"""One module per ``appfusion`` subcommand; each defines ``register(subparsers)``."""
