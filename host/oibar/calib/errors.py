"""The one exception the toolbox raises for bad input; the CLI prints it as one line, exit 2."""


class CalibError(ValueError):
    pass
