#!/usr/bin/env python3
"""Solve a system exported by `stickslip export` with PETSc over MPI.

    mpiexec -n 2 python3 scripts/petsc_solve.py EXPORT_DIR [--out y.petsc] [PETSc options]

Reads EXPORT_DIR/hhat.petsc (the eliminated Hessian, block size from hhat.petsc.info)
and EXPORT_DIR/bhat.petsc, solves with KSP (default: CG with point-block Jacobi,
relative tolerance 1e-12; any -ksp_type / -pc_type / -ksp_rtol option overrides), and
writes the solution y as a PETSc binary Vec (default EXPORT_DIR/y.petsc) for
`stickslip recover`. Prints one JSON line with iterations, residual and seconds.

Debian's python3-petsc4py finds PETSc through PETSC_DIR; when it is unset the script
uses the real-scalar build under /usr/lib/petscdir.
"""
import glob
import json
import os
import sys
import time


def find_petsc_dir():
    if os.environ.get("PETSC_DIR"):
        return
    # The 32-bit-index real build: the export writes 32-bit PetscInt (a "-64-real"
    # build would misread it).
    for d in sorted(glob.glob("/usr/lib/petscdir/petsc*/*-real")):
        if "-64-" in os.path.basename(d):
            continue
        os.environ["PETSC_DIR"] = d
        sys.path.append(os.path.join(d, "lib/python3/dist-packages"))
        return


def main():
    find_petsc_dir()
    import petsc4py

    args = [a for a in sys.argv[1:]]
    if not args or args[0].startswith("-"):
        print("usage: petsc_solve.py EXPORT_DIR [--out y.petsc] [PETSc options]", file=sys.stderr)
        return 2
    export_dir = args.pop(0)
    out = os.path.join(export_dir, "y.petsc")
    if "--out" in args:
        k = args.index("--out")
        out = args[k + 1]
        del args[k : k + 2]
    petsc4py.init([sys.argv[0]] + args)
    from petsc4py import PETSc

    comm = PETSc.COMM_WORLD
    opts = PETSc.Options()
    # Defaults; command-line options win because setFromOptions runs after.
    if not opts.hasName("ksp_type"):
        opts["ksp_type"] = "cg"
    if not opts.hasName("pc_type"):
        opts["pc_type"] = "pbjacobi"
    if not opts.hasName("ksp_rtol"):
        opts["ksp_rtol"] = 1e-12
    if not opts.hasName("ksp_max_it"):
        opts["ksp_max_it"] = 100000

    t0 = time.perf_counter()
    viewer = PETSc.Viewer().createBinary(os.path.join(export_dir, "hhat.petsc"), "r", comm=comm)
    A = PETSc.Mat().create(comm=comm)
    A.setType(PETSc.Mat.Type.AIJ)
    A.setFromOptions()
    A.load(viewer)
    A.setOption(PETSc.Mat.Option.SPD, True)
    vb = PETSc.Viewer().createBinary(os.path.join(export_dir, "bhat.petsc"), "r", comm=comm)
    # Load b into the matrix's row layout (multiples of the block size per rank).
    b = A.createVecLeft()
    b.load(vb)
    x = b.duplicate()
    x.set(0.0)
    t_load = time.perf_counter() - t0

    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOperators(A)
    ksp.setFromOptions()
    t1 = time.perf_counter()
    ksp.solve(b, x)
    t_solve = time.perf_counter() - t1

    r = b.duplicate()
    A.mult(x, r)
    r.aypx(-1.0, b)
    rel = r.norm() / max(b.norm(), 1e-300)
    reason = ksp.getConvergedReason()

    w = PETSc.Viewer().createBinary(out, "w", comm=comm)
    x.view(w)
    w.destroy()
    if comm.getRank() == 0:
        print(
            json.dumps(
                {
                    "ranks": comm.getSize(),
                    "ksp": ksp.getType(),
                    "pc": ksp.getPC().getType(),
                    "block_size": A.getBlockSize(),
                    "iterations": ksp.getIterationNumber(),
                    "converged_reason": int(reason),
                    "relative_residual": rel,
                    "seconds": {"load": t_load, "solve": t_solve},
                    "out": out,
                }
            )
        )
    return 0 if reason > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
