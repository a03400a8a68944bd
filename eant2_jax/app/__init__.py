"""Applications built on the library: the ``eant2`` command line (`.cli`), the paper's
experiments (`.experiments`) and the reports of run directories (`.report`).

The library (everything outside this subpackage) never prints and never imports from here.
"""
