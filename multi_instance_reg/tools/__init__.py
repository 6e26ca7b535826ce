"""Command-line tools (``mireg``). They sit beside the library and never inside it."""
