"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""

from __future__ import annotations


class UserError(Exception):
    """Bad input or environment: the message names the problem and the fix, in one line."""


class MissingWeightsError(UserError):
    """Model weights are not available locally and cannot be downloaded."""
