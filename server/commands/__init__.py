"""The `scalesteer` command line: one module per subcommand, loaded only when chosen."""
