"""The one exception type users see: bad input, described in a single line; and other exceptions in one line."""


class WarpbagsError(Exception):
    """Bad input or an unusable file; the message names the offending file or value in one line.

    The CLI prints it without a traceback and exits non-zero; library users can catch it.
    """


def one_line(error: BaseException, limit: int = 200) -> str:
    """`error` as "Type: first line of its message", at most `limit` characters: what a one-line report of an
    exception from another library (a checkpoint torch cannot read, a metric package that will not import) says."""
    lines = str(error).splitlines()
    return f"{type(error).__name__}: {lines[0] if lines else ''}"[:limit]
