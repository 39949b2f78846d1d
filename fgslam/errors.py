"""Errors that are the user's input, not the program's: the CLI prints them as one line."""


class UserError(Exception):
    """Bad input (file, option, data); the message is complete and meant for the user."""
