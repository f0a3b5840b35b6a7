"""The README's notebook example runs as written (doctest), so it cannot drift from the API."""

from __future__ import annotations

import doctest

from conftest import ROOT


def test_readme_notebook_example_runs():
    result = doctest.testfile(
        str(ROOT / "README.md"),
        module_relative=False,
        optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
        verbose=False,
    )
    assert result.attempted >= 5, "the README lost its doctest example"
    assert result.failed == 0
