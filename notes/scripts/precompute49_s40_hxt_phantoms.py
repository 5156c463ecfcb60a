"""python notes/scripts/precompute49_s40_hxt_phantoms.py NAVAPP-ARGS: navapp's CLI with HXT (no Netgen) first in every plan, phantoms included: what a changed phantom mesh would do (measured, not navapp's behaviour)."""
import sys
from dataclasses import replace
from navapp.anatomy import meshing
a = meshing.ATTEMPTS
meshing.plan_mesh.__defaults__ = ((replace(a[0], volume="hxt"),) + a, None)
from navapp.cli import main
sys.exit(main(sys.argv[1:]))
