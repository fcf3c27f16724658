"""The package's version (a module of its own: any module may read it without
importing the package's ``__init__``)."""

__version__ = "0.2.0.dev0"
