"""`bid` subcommands of the model package (registered through the "bid.commands" entry point)."""

from __future__ import annotations

import argparse


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add the model's subcommands (train, gradcam, ...) to the `bid` parser."""
