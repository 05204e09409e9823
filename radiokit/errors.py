"""The exceptions radiokit raises on purpose."""

from radiokit._names import shown


class RadiokitError(Exception):
    """Base class of every error radiokit raises on purpose."""


class FormatError(RadiokitError, ValueError):
    """A file is not what it claims or what was asked for.

    The message always names the file and what is wrong with it. ``advice`` maps each reader
    option the message advises (``"allow_external"``, ``"dataset"``) to the very words that advise
    it, so that a command without that option (``radiokit process``) says its own remedy in their
    place by this field, not by matching the text: a rewording of the reader's message cannot
    silently leave the wrong advice.
    """

    def __init__(self, path, problem, *, advice=None):
        self.path = str(path)
        self.problem = problem
        self.advice = dict(advice or {})
        super().__init__(f"{shown(self.path)}: {problem}")  # a newline in its name printed raw (s50)

    def __reduce__(self):
        # an exception is rebuilt from its args, the whole message: the path and the fields were lost
        return _format_error, (type(self), self.path, self.problem, self.advice)


def _format_error(kind, path, problem, advice):
    return kind(path, problem, advice=advice)


class InputErrors(RadiokitError, ValueError):
    """Several inputs of one command are bad: ``errors`` holds each one's own error, in the order
    the inputs were given; the message is their messages, one line each.

    Why: a command given several files named only the first bad one and stopped, and the user
    met the next one only after fixing it. Inputs that are cheap to judge (their headers) are
    judged all first (:func:`radiokit.io.judge_all`), and every bad one is named at once."""

    def __init__(self, errors):
        self.errors = list(errors)
        super().__init__("\n".join(str(e) for e in self.errors))

    def __reduce__(self):
        # rebuilt from its args, the message, that text was taken for the errors: one character a line
        return type(self), (self.errors,)
