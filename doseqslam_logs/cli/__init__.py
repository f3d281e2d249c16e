"""The `doseqslam-logs` command: one module per subcommand, each parsing its arguments and
calling the library."""
