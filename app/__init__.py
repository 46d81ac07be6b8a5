"""trifuse application edge: sources, files on disk, the server and the CLI."""
