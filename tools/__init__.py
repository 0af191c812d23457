"""The followbus command line."""
