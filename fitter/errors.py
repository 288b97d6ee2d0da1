"""One family of user errors: every mistake a user can make is a ``FitterError``.

The message is one sentence naming the file, key or value and what to change;
the CLI prints it and exits 2 without a traceback. Internal faults are any
other exception.
"""


class FitterError(ValueError):
    """Base of every user error (bad config, image, scene, material, fit request)."""
