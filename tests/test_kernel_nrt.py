"""The mechanics kernels free every array they allocate (numba's runtime statistics).

Most kernels are compiled without numba's reference counting (``_nrt=False``, the rule at the
top of ``ctrplan/shape/_ode.py``): such a kernel must never hand an array back to a caller that
counts references, or the caller would release a reference that was never taken (a double free)
or keep one that is never released (a leak). Oracle: numba's own allocation counters
(``NUMBA_NRT_STATS=1``), which count every allocation and free the runtime makes, in a fresh
process. Over repeated solves (after one warm-up, which may fill caches) allocations and frees
must balance exactly: unloaded rigid and compliant, loaded (gravity and a tip force), the
bistable robot with its stability check, and chained (continuation) solves.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = textwrap.dedent("""
    import numpy as np
    from numba.core.runtime import rtsys
    from ctrplan.robot import load_robot
    from ctrplan.shape import branches
    from ctrplan.shape.physics import Loads, PhysicsModel

    seed1, nylon = load_robot("seed1"), load_robot("two_tube_nylon")
    q1, qn = seed1.sample(64, seed=3), nylon.sample(64, seed=4)
    loads = Loads(gravity=(0.0, -9.80665, 0.0), tip_force=(0.05, 0.0, 0.02))
    models = [PhysicsModel(seed1, torsion=False), PhysicsModel(seed1, torsion=True),
              PhysicsModel(seed1, torsion=True, loads=loads),
              PhysicsModel(seed1, torsion=False, loads=loads), PhysicsModel(nylon, torsion=True)]
    chain = np.zeros(len(qn), bool)
    chain[::16] = True
    path = np.linspace(qn[0], qn[1], len(qn))

    def solve_all():
        for m, q in zip(models, (q1, q1, q1, q1, qn)):
            m.shape(q, 20)
        branches.solve(models[-1], path, 20, chain=chain, uz_init=np.full((len(qn), 2), np.nan))

    solve_all()
    a = rtsys.get_allocation_stats()
    for _ in range(3):
        solve_all()
    b = rtsys.get_allocation_stats()
    print(b.alloc - a.alloc, b.free - a.free, b.mi_alloc - a.mi_alloc, b.mi_free - a.mi_free)
""")


def test_kernels_free_every_array_they_allocate():
    env = dict(os.environ, NUMBA_NRT_STATS="1", PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env,
                       cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    alloc, free, mi_alloc, mi_free = map(int, r.stdout.split()[-4:])
    assert alloc > 0                        # the batch entry points do allocate
    assert (alloc, mi_alloc) == (free, mi_free), r.stdout
