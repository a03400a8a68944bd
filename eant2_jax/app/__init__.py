"""Applications built on the library: the ``eant2`` command line (:mod:`.cli`), the paper's
experiments (:mod:`.experiments`) and the reports of run directories (:mod:`.report`).

The library (everything outside this subpackage) never prints and never imports from here.
"""
