"""Argument types shared by the scripts (``python scripts/NAME.py`` puts this folder on the path)."""

from __future__ import annotations

import argparse
import os

__all__ = ["positive_int", "out_dir"]


def positive_int(text: str) -> int:
    """An ``argparse`` type: a positive integer; the error names the value."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def out_dir(text: str) -> str:
    """An ``argparse`` type: an output folder, made if needed; not empty, not an existing file."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must name a folder, got an empty path")
    if os.path.exists(text) and not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a folder")
    return text
