"""The ``skyloop`` command (``main``): its subcommands' command lines, generated from
settings dataclasses with tyro (``dataclass_cli``, ``settings_base``)."""
