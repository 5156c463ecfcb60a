"""navapp: sparse-data liver deformation correction by linearized iterative boundary
reconstruction (LIBR; Heiselman & Miga, IEEE TMI 2020).

Sub-packages, in the one direction data flows:
anatomy -> mechanics -> simulation -> registration -> evaluation; ``app`` only calls them.
All lengths are millimetres unless a docstring says otherwise.
"""

__version__ = "0.1.0"
