"""The exceptions radiokit raises on purpose."""


class RadiokitError(Exception):
    """Base class of every error radiokit raises on purpose."""


class FormatError(RadiokitError, ValueError):
    """A file is not what it claims or what was asked for.

    The message always names the file and what is wrong with it.
    """

    def __init__(self, path, problem):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class InputErrors(RadiokitError, ValueError):
    """Several inputs of one command are bad: ``errors`` holds each one's own error, in the order
    the inputs were given; the message is their messages, one line each.

    Why: a command given several files named only the first bad one and stopped, and the user
    met the next one only after fixing it. Inputs that are cheap to judge (their headers) are
    judged all first (:func:`radiokit.io.judge_all`), and every bad one is named at once."""

    def __init__(self, errors):
        self.errors = list(errors)
        super().__init__("\n".join(str(e) for e in self.errors))
