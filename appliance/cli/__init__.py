"""The ``viper`` command: one thin module per subcommand.

Each module in this package that defines ``register(subparsers)`` adds its subcommand(s); the
handler it sets (``set_defaults(func=...)``) receives the parsed arguments and returns an exit code.
"""
