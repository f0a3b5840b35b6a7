"""The ``replay`` command line: the only package that imports click."""
