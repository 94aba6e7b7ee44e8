"""User-facing error type: bad input is reported with what, where and how to fix it."""


class NeuralMapError(ValueError):
    """Raised for bad user input (files, configs, shapes, values).

    The message always states what is wrong, where (file, config key, argument) and how to
    fix it. Command-line entry points catch it and print the message without a traceback.
    """
