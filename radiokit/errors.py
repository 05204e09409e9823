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
