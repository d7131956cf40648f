"""The one exception type users see: bad input, described in a single line."""


class WarpbagsError(Exception):
    """Bad input or an unusable file; the message names the offending file or value in one line.

    The CLI prints it without a traceback and exits non-zero; library users can catch it.
    """
