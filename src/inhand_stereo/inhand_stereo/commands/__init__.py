"""Command-line tools: parse arguments, call the library, report."""
