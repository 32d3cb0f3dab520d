"""The error a command reports as the user's mistake (``cli.main``: one line, exit status 2)."""


class UserError(ValueError):
    """A mistake in what the user asked for (a flag, a setting, an input file's content): the
    command line prints it as one line ``error: ...`` with exit status 2 (``cli.main``).

    A ValueError, so code and tests that catch ValueError keep working; raise it (or a subclass)
    where the user can fix the cause, and a plain ValueError where only a bug can reach the check.
    """
