"""Command-line tools: coopctl (offline map tools now; daemon control subcommands later)."""
