"""Small dense linear algebra without allocation (the shape a C port takes).

The estimators solve systems of at most a dozen unknowns. numpy's
``linalg`` allocates its results and workspaces on every call, so the
firmware's steady-state tick uses these routines instead: they read and
write preallocated float64 buffers through flat memoryviews (``flat(a)``,
row-major, element ``(i, j)`` of an ``n x n`` matrix at ``i * n + j``) and
compute with Python floats. Nothing here creates a numpy array.

* ``cholesky`` / ``chol_solve`` / ``chol_inverse``: symmetric positive
  definite systems (Kalman innovation covariances, Levenberg-Marquardt
  normal equations).
* ``jacobi_eigh``: symmetric eigen-decomposition by cyclic Jacobi rotations
  (Kuipers' eigenvector, the robust inverse of an information matrix, the
  quaternion of the nearest rotation).
* ``nearest_rotation``: the proper rotation closest to a 3x3 matrix in the
  Frobenius norm, as the largest eigenvector of Horn's 4x4 quaternion matrix
  (the orthogonal Procrustes / polar factor, what an SVD with det +1 gives).
* ``rotvec_from_matrix``: the rotation vector (matrix logarithm) of a rotation.
* ``inv3_sym``: the inverse of a symmetric positive definite 3x3 (adjugate
  over determinant), the one 3x3 inverse of the firmware (innovation
  covariances of 3-dof updates, the coil-choice posterior).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.rotation import matrix_from_quat

_sqrt = math.sqrt


def flat(a: np.ndarray) -> memoryview:
    """A 1-D float64 memoryview over a C-contiguous array (made once, at start-up)."""
    if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous):
        raise ValueError("flat() needs a C-contiguous float64 array")
    return memoryview(a.reshape(-1))


def float_view(a):
    """A C-ordered float64 array as a memoryview, whose elements read as Python floats (the
    same values, without a numpy scalar per element: the arithmetic on them is several times
    faster); anything else as it is."""
    if isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous:
        return memoryview(a)
    return a


def cholesky(a, n: int, L) -> bool:
    """Lower Cholesky factor of the symmetric ``n x n`` matrix ``a`` into ``L``
    (upper triangle of ``L`` zeroed). Returns False (``L`` undefined) when a
    pivot is not positive or not finite, i.e. ``a`` is not positive definite."""
    for j in range(n):
        jn = j * n
        s = a[jn + j]
        for k in range(j):
            v = L[jn + k]
            s -= v * v
        if not s > 0.0 or s == math.inf:
            return False
        d = _sqrt(s)
        L[jn + j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            inn = i * n
            s = a[inn + j]
            for k in range(j):
                s -= L[inn + k] * L[jn + k]
            L[inn + j] = s * inv
        for i in range(j + 1, n):
            L[jn + i] = 0.0
    return True


def chol_solve(L, n: int, b, x) -> None:
    """Solve ``L L^T x = b`` (``b`` and ``x`` may be the same buffer)."""
    for i in range(n):
        s = b[i]
        inn = i * n
        for k in range(i):
            s -= L[inn + k] * x[k]
        x[i] = s / L[inn + i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k * n + i] * x[k]
        x[i] = s / L[i * n + i]


def chol_inverse(a, n: int, out, L) -> bool:
    """``out = a^-1`` for a symmetric positive definite ``a`` (``L`` scratch,
    ``n * n``). ``out`` must not alias ``a`` or ``L``. Returns False, leaving
    ``out`` undefined, when ``a`` is not positive definite."""
    if not cholesky(a, n, L):
        return False
    # L^-1 (lower triangular) in place of L
    for j in range(n):
        jn = j * n
        L[jn + j] = 1.0 / L[jn + j]
        for i in range(j + 1, n):
            inn = i * n
            s = 0.0
            for k in range(j, i):
                s -= L[inn + k] * L[k * n + j]
            L[inn + j] = s / L[inn + i]
    # a^-1 = L^-T L^-1
    for i in range(n):
        for j in range(i, n):
            s = 0.0
            for k in range(j, n):
                kn = k * n
                s += L[kn + i] * L[kn + j]
            out[i * n + j] = s
            out[j * n + i] = s
    return True



def _cholesky_lines(n: int, damped: bool) -> list:
    """Straight-line :func:`cholesky` of the lower triangle of the flat ``a``
    into locals ``l{i}_{j}`` (and ``r{j} = 1 / l{j}_{j}``); ``damped``: the
    diagonal read as :func:`coiltrack.firmware.pose.lm.damped` makes it
    (``d + lam * d``, ``d + lam`` when ``d <= 0``)."""
    ln = []
    for i in range(n):
        for j in range(i + 1):
            ln.append(f"    a{i}_{j} = a[{i * n + j}]")
        if damped:
            ln.append(f"    a{i}_{i} += lam * (1.0 if a{i}_{i} <= 0.0 else a{i}_{i})")
    for j in range(n):
        ln.append(f"    s = a{j}_{j}" + "".join(f" - l{j}_{k} * l{j}_{k}" for k in range(j)))
        ln.append("    if not s > 0.0 or s == INF:")
        ln.append("        return False")
        ln.append(f"    l{j}_{j} = sqrt(s)")
        ln.append(f"    r{j} = 1.0 / l{j}_{j}")
        for i in range(j + 1, n):
            ln.append(f"    l{i}_{j} = (a{i}_{j}" + "".join(f" - l{i}_{k} * l{j}_{k}" for k in range(j)) + f") * r{j}")
    return ln


def _spd_inverse_source(n: int) -> str:
    """Straight-line source of :func:`chol_inverse` for one size ``n`` (what a C
    compiler makes of its loops once ``n`` is a constant; PX4's EKF2 fuses
    with generated straight-line code the same way): the lower triangle read
    into locals, the Cholesky factor, its inverse and ``L^-T L^-1`` in the same
    order of operations as the loops, so the result is the same to the bit."""
    ln = [f"def spd_inverse_{n}(a, out):"] + _cholesky_lines(n, False)
    for j in range(n):                     # L^-1 (chol_inverse, first loop): m_ij
        ln.append(f"    m{j}_{j} = r{j}")
        for i in range(j + 1, n):
            terms = "".join(f" - l{i}_{k} * m{k}_{j}" for k in range(j, i))
            ln.append(f"    m{i}_{j} = (-{terms[3:]}) / l{i}_{i}")
    for i in range(n):                     # L^-T L^-1 (chol_inverse, second loop)
        for j in range(i, n):
            ln.append("    s = " + " + ".join(f"m{k}_{i} * m{k}_{j}" for k in range(j, n)))
            ln.append(f"    out[{i * n + j}] = s")
            if i != j:
                ln.append(f"    out[{j * n + i}] = s")
    ln.append("    return True")
    return "\n".join(ln) + "\n"


def _damped_solve_source(n: int) -> str:
    """Straight-line source of ``damped``, :func:`cholesky` and
    :func:`chol_solve` for one size ``n``, in the loops' order of operations."""
    ln = [f"def damped_spd_solve_{n}(a, b, x, lam):"] + _cholesky_lines(n, True)
    for i in range(n):                     # L y = b
        ln.append(f"    y{i} = (b[{i}]" + "".join(f" - l{i}_{k} * y{k}" for k in range(i)) + f") / l{i}_{i}")
    for i in range(n - 1, -1, -1):         # L^T x = y
        ln.append(f"    x{i} = (y{i}" + "".join(f" - l{k}_{i} * x{k}" for k in range(i + 1, n)) + f") / l{i}_{i}")
        ln.append(f"    x[{i}] = x{i}")
    ln.append("    return True")
    return "\n".join(ln) + "\n"


def _c_expr(py: str) -> str:
    """A line of the straight-line Python above as C (the same operations, same order)."""
    return py.replace("not s > 0.0 or s == INF", "!(s > 0.0) || s == INFINITY")


def _damped_solve_c_source(n: int) -> str:
    """:func:`_damped_solve_source` for ``n`` emitted as a C99 function
    ``int ct_damped_spd_solve_<n>(const double *a, const double *b, double *x, double lam)``:
    the same lines, so with ``-ffp-contract=off`` the same result to the bit (the compiled
    core's Levenberg-Marquardt step, ``core/src/lm.c``)."""
    out = [f"int ct_damped_spd_solve_{n}(const double *a, const double *b, double *x, double lam)", "{",
           "    double s;"]
    decl = [f"a{i}_{j}" for i in range(n) for j in range(i + 1)] + [f"l{i}_{j}" for i in range(n) for j in range(i + 1)]
    decl += [f"r{j}" for j in range(n - 1)] + [f"y{i}" for i in range(n)] + [f"x{i}" for i in range(n)]
    for k in range(0, len(decl), 12):
        out.append("    double " + ", ".join(decl[k:k + 12]) + ";")
    for line in _damped_solve_source(n).splitlines()[1:]:
        body = line.strip()
        ind = "    " * ((len(line) - len(line.lstrip())) // 4)
        if body.startswith(f"r{n - 1} = "):
            continue                       # the last reciprocal is not read (the Python's is dead)
        if body.startswith("if "):
            out.append(f"{ind}if ({_c_expr(body[3:-1])})")
        elif body == "return False":
            out.append(f"{ind}return 0;")
        elif body == "return True":
            out.append(f"{ind}return 1;")
        elif "+= lam * (1.0 if " in body:
            v = body.split(" ")[0]
            out.append(f"{ind}{v} += lam * ({v} <= 0.0 ? 1.0 : {v});")
        else:
            out.append(f"{ind}{body};")
    out.append("}")
    return "\n".join(out) + "\n"


#: the sizes of the straight-line C the compiled core carries (``core/src/linalg_gen.c``)
C_GENERATED = (("damped_spd_solve", 6), ("damped_spd_solve", 3))


def generated_c() -> str:
    """The text of ``core/src/linalg_gen.c``: every function of :data:`C_GENERATED`, emitted
    from the same generators as the Python (``tests/firmware/core`` checks the file is this)."""
    head = ["/*", " * Generated by coiltrack.firmware.linalg.generated_c(): do not edit.",
            " * Straight-line C of linalg's generated Python, the same operations in the same order.",
            " */", "#include <math.h>", "", '#include "coiltrack_core.h"', ""]
    funcs = [{"damped_spd_solve": _damped_solve_c_source}[kind](n) for kind, n in C_GENERATED]
    return "\n".join(head) + "\n".join(funcs)


_GENERATED: dict = {}


def _generated(kind: str, n: int, source):
    f = _GENERATED.get((kind, n))
    if f is None:
        if not 1 <= n <= 16:
            raise ValueError(f"{kind}: size {n} outside 1..16")
        env = {"sqrt": _sqrt, "INF": math.inf, "_sort_eigen": _sort_eigen}
        exec(compile(source(n), f"<{kind}_{n}>", "exec"), env)
        f = _GENERATED[(kind, n)] = env[f"{kind}_{n}"]
    return f


def spd_inverse(n: int):
    """The function ``inv(a, out) -> bool`` that does :func:`chol_inverse` for
    size ``n`` without its loops (flat ``a`` and ``out`` of ``n * n``, lower
    triangle of ``a`` read; ``out`` may not alias ``a``; False, ``out``
    undefined, when ``a`` is not positive definite). Made once per size at
    start-up: about five times faster than the loops at ``n = 9`` (no index
    arithmetic, no buffer reads of intermediate values); same result to the bit."""
    return _generated("spd_inverse", n, _spd_inverse_source)


def damped_spd_solve(n: int):
    """The function ``solve(a, b, x, lam) -> bool``: ``x = (a + lam diag(a))^-1 b``
    (a diagonal element ``<= 0`` damped by ``lam`` alone; the Levenberg-Marquardt
    system of ``pose.lm``) by Cholesky, the straight-line form of ``damped``,
    :func:`cholesky` and :func:`chol_solve` for size ``n`` (flat ``a`` read in
    its lower triangle, ``b`` and ``x`` of ``n``; same result to the bit). False,
    ``x`` untouched, when the damped matrix is not positive definite."""
    return _generated("damped_spd_solve", n, _damped_solve_source)

def lu_factor(K, n: int, perm) -> bool:
    """LU with partial pivoting of the ``n x n`` matrix ``K`` (row-major flat) in place, the row
    permutation into ``perm`` (n); False if a pivot is below 1e-12 (singular)."""
    for i in range(n):
        perm[i] = i
    for c in range(n):
        piv, best = c, abs(K[n * c + c])
        for r in range(c + 1, n):
            if abs(K[n * r + c]) > best:
                piv, best = r, abs(K[n * r + c])
        if not best > 1e-12:
            return False
        if piv != c:
            for j in range(n):
                K[n * c + j], K[n * piv + j] = K[n * piv + j], K[n * c + j]
            perm[c], perm[piv] = perm[piv], perm[c]
        d = K[n * c + c]
        for r in range(c + 1, n):
            f = K[n * r + c] / d
            K[n * r + c] = f
            for j in range(c + 1, n):
                K[n * r + j] -= f * K[n * c + j]
    return True


def lu_solve(K, n: int, perm, e, y) -> None:
    """``e <- K^-1 e`` with the factors of :func:`lu_factor`; ``y`` (n) scratch."""
    for i in range(n):
        acc = e[perm[i]]
        for j in range(i):
            acc -= K[n * i + j] * y[j]
        y[i] = acc
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for j in range(i + 1, n):
            acc -= K[n * i + j] * e[j]
        e[i] = acc / K[n * i + i]


#: cyclic sweeps at most of :func:`jacobi_eigh`
JACOBI_SWEEPS = 60


def jacobi_eigh_of(n: int):
    """The function ``eigh(a, w, v, sweeps)`` that :func:`jacobi_eigh` runs for size ``n``, made
    now: a caller on the tick takes it at start-up, so the first tick that needs it does not
    generate and compile its source (2-3 ms)."""
    return _generated("jacobi_eigh", n, _jacobi_source)


def jacobi_eigh(a, n: int, w, v, sweeps: int = JACOBI_SWEEPS) -> None:
    """Eigen-decomposition of a symmetric ``n x n`` matrix by cyclic Jacobi
    rotations (Golub & Van Loan, sec. 8.5). ``a`` is overwritten; eigenvalues
    go to ``w`` (ascending), unit eigenvectors to the columns of ``v``
    (``v[i * n + k]`` is component ``i`` of eigenvector ``k``). Stops when the
    off-diagonal mass is below 1e-30 of the total (or after ``sweeps``).

    Runs the straight-line form of :func:`jacobi_eigh_loops` for ``n`` (made once per
    size, :func:`_jacobi_source`): the same operations in the same order, the same
    result to the bit, three to four times faster."""
    _generated("jacobi_eigh", n, _jacobi_source)(a, w, v, sweeps)


def _jacobi_source(n: int) -> str:
    """Straight-line source of :func:`jacobi_eigh_loops` for one size ``n``: the matrix
    and the eigenvectors in locals ``a{i}_{j}``, ``v{i}_{j}`` (every element, as the loops
    read and write both triangles), each sweep's test and rotations written out in the
    loops' order (a rotation of a zero element skipped as there), the results stored
    back and sorted by the loops' selection sort."""
    ln = [f"def jacobi_eigh_{n}(a, w, v, sweeps):"]
    for i in range(n):
        ln.append("    " + "; ".join(f"a{i}_{j} = a[{i * n + j}]" for j in range(n)))
        ln.append("    " + "; ".join(f"v{i}_{j} = {'1.0' if i == j else '0.0'}" for j in range(n)))
    ln.append("    for _ in range(sweeps):")
    ln.append("        off = 0.0")
    ln.append("        tot = 0.0")
    for p in range(n):
        ln.append(f"        tot += a{p}_{p} * a{p}_{p}")
        for q in range(p + 1, n):
            ln.append(f"        off += a{p}_{q} * a{p}_{q}")
    ln.append("        tot += 2.0 * off")
    ln.append("        if off <= 1e-30 * tot or off == 0.0:")
    ln.append("            break")
    for p in range(n - 1):
        for q in range(p + 1, n):
            ln.append(f"        apq = a{p}_{q}")
            ln.append("        if apq != 0.0:")
            ln.append(f"            app = a{p}_{p}")
            ln.append(f"            aqq = a{q}_{q}")
            ln.append("            theta = (aqq - app) / (2.0 * apq)")
            ln.append("            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + sqrt(theta * theta + 1.0))")
            ln.append("            c = 1.0 / sqrt(t * t + 1.0)")
            ln.append("            s = t * c")
            ln.append(f"            a{p}_{p} = app - t * apq")
            ln.append(f"            a{q}_{q} = aqq + t * apq")
            ln.append(f"            a{p}_{q} = 0.0")
            ln.append(f"            a{q}_{p} = 0.0")
            for r in range(n):
                if r != p and r != q:
                    ln.append(f"            arp = a{r}_{p}")
                    ln.append(f"            arq = a{r}_{q}")
                    ln.append("            nrp = c * arp - s * arq")
                    ln.append("            nrq = s * arp + c * arq")
                    ln.append(f"            a{r}_{p} = nrp")
                    ln.append(f"            a{p}_{r} = nrp")
                    ln.append(f"            a{r}_{q} = nrq")
                    ln.append(f"            a{q}_{r} = nrq")
                ln.append(f"            vrp = v{r}_{p}")
                ln.append(f"            vrq = v{r}_{q}")
                ln.append(f"            v{r}_{p} = c * vrp - s * vrq")
                ln.append(f"            v{r}_{q} = s * vrp + c * vrq")
    for i in range(n):
        ln.append("    " + "; ".join(f"a[{i * n + j}] = a{i}_{j}" for j in range(n)))
        ln.append("    " + "; ".join(f"v[{i * n + j}] = v{i}_{j}" for j in range(n)))
    ln.append(f"    _sort_eigen(a, {n}, w, v)")
    return "\n".join(ln) + "\n"


def _sort_eigen(a, n: int, w, v) -> None:
    """The diagonal of ``a`` into ``w``, ascending, the columns of ``v`` following
    (selection sort)."""
    for i in range(n):
        w[i] = a[i * n + i]
    for i in range(n - 1):
        k = i
        for j in range(i + 1, n):
            if w[j] < w[k]:
                k = j
        if k != i:
            t = w[i]
            w[i] = w[k]
            w[k] = t
            for r in range(n):
                rn = r * n
                t = v[rn + i]
                v[rn + i] = v[rn + k]
                v[rn + k] = t


def jacobi_eigh_loops(a, n: int, w, v, sweeps: int = 60) -> None:
    """:func:`jacobi_eigh` by its loops (the definition the straight-line code is
    written from and tested against)."""
    for i in range(n):
        for j in range(n):
            v[i * n + j] = 1.0 if i == j else 0.0
    for _ in range(sweeps):
        off = 0.0
        tot = 0.0
        for p in range(n):
            pn = p * n
            tot += a[pn + p] * a[pn + p]
            for q in range(p + 1, n):
                x = a[pn + q]
                off += x * x
        tot += 2.0 * off
        if off <= 1e-30 * tot or off == 0.0:
            break
        for p in range(n - 1):
            pn = p * n
            for q in range(p + 1, n):
                apq = a[pn + q]
                if apq == 0.0:
                    continue
                qn = q * n
                app = a[pn + p]
                aqq = a[qn + q]
                theta = (aqq - app) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + _sqrt(theta * theta + 1.0))
                c = 1.0 / _sqrt(t * t + 1.0)
                s = t * c
                a[pn + p] = app - t * apq
                a[qn + q] = aqq + t * apq
                a[pn + q] = 0.0
                a[qn + p] = 0.0
                for r in range(n):
                    if r != p and r != q:
                        rn = r * n
                        arp = a[rn + p]
                        arq = a[rn + q]
                        nrp = c * arp - s * arq
                        nrq = s * arp + c * arq
                        a[rn + p] = nrp
                        a[pn + r] = nrp
                        a[rn + q] = nrq
                        a[qn + r] = nrq
                    rn = r * n
                    vrp = v[rn + p]
                    vrq = v[rn + q]
                    v[rn + p] = c * vrp - s * vrq
                    v[rn + q] = s * vrp + c * vrq
    _sort_eigen(a, n, w, v)


#: largest element of ``M^T M - I`` that :func:`nearest_rotation` takes as a rotation already
ORTHONORMAL_TOL = 1e-12


def _is_rotation(m00, m01, m02, m10, m11, m12, m20, m21, m22) -> bool:
    """``M^T M = I`` to ``ORTHONORMAL_TOL`` per element and ``det M > 0`` (False for NaN)."""
    tol = ORTHONORMAL_TOL
    if not (abs(m00 * m00 + m10 * m10 + m20 * m20 - 1.0) < tol and abs(m01 * m01 + m11 * m11 + m21 * m21 - 1.0) < tol
            and abs(m02 * m02 + m12 * m12 + m22 * m22 - 1.0) < tol):
        return False
    if not (abs(m00 * m01 + m10 * m11 + m20 * m21) < tol and abs(m00 * m02 + m10 * m12 + m20 * m22) < tol
            and abs(m01 * m02 + m11 * m12 + m21 * m22) < tol):
        return False
    return m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20) > 0.0


class Rot3:
    """Scratch for ``nearest_rotation`` (a 4x4 matrix, its eigenvectors and
    eigenvalues), allocated once."""

    def __init__(self):
        self._k = np.zeros(16)
        self._v = np.zeros(16)
        self._w = np.zeros(4)
        self.k = flat(self._k)
        self.v = flat(self._v)
        self.w = flat(self._w)
        self.eigh = jacobi_eigh_of(4)


def nearest_rotation(m, out, work: Rot3) -> None:
    """Proper rotation maximising ``trace(R^T M)`` (closest in the Frobenius
    norm) into ``out`` (3x3, indexable as ``out[i, j]``); ``m`` is a flat
    sequence of 9 (row-major).

    Horn (1987) / Bar-Itzhack (2000): with ``R = R(q)`` (unit quaternion
    ``q = (w, x, y, z)``), ``trace(R^T M) = q^T K q`` with the symmetric
    4x4 ``K`` below, so the optimum is the eigenvector of the largest
    eigenvalue of ``K``. The result equals the SVD projection
    ``U diag(1, 1, det(U V^T)) V^T``.

    A proper rotation already (``|M^T M - I|`` below ``ORTHONORMAL_TOL`` in
    every element, ``det M > 0``: a warm start or an LM iterate, whose
    rounding drift is ~1e-15) is copied as it is: its projection differs
    from it by less than the tolerance, and the eigen-decomposition is the
    costliest part of starting and finishing a pose solve.
    """
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8])
    if _is_rotation(m00, m01, m02, m10, m11, m12, m20, m21, m22):
        out[0, 0], out[0, 1], out[0, 2] = m00, m01, m02
        out[1, 0], out[1, 1], out[1, 2] = m10, m11, m12
        out[2, 0], out[2, 1], out[2, 2] = m20, m21, m22
        return
    k = work.k
    k[0] = m00 + m11 + m22
    k[1] = k[4] = m21 - m12
    k[2] = k[8] = m02 - m20
    k[3] = k[12] = m10 - m01
    k[5] = m00 - m11 - m22
    k[6] = k[9] = m01 + m10
    k[7] = k[13] = m02 + m20
    k[10] = -m00 + m11 - m22
    k[11] = k[14] = m12 + m21
    k[15] = -m00 - m11 + m22
    work.eigh(k, work.w, work.v, JACOBI_SWEEPS)     # jacobi_eigh(k, 4, work.w, work.v)
    v = work.v
    qw, qx, qy, qz = v[3], v[7], v[11], v[15]
    nrm = _sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw /= nrm
    qx /= nrm
    qy /= nrm
    qz /= nrm
    matrix_from_quat((qw, qx, qy, qz), out)


def rotvec_from_matrix(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Rotation vector ``w`` with ``exp([w]x) = R`` (|w| <= pi), from the nine
    elements of a rotation matrix (row-major). Accurate for small angles
    (series) and near pi (from the symmetric part)."""
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    vx = 0.5 * (r21 - r12)
    vy = 0.5 * (r02 - r20)
    vz = 0.5 * (r10 - r01)
    s = _sqrt(vx * vx + vy * vy + vz * vz)       # sin(angle)
    if c > 0.0:
        angle = math.atan2(s, c)
        f = 1.0 + angle * angle / 6.0 if s < 1e-8 else angle / s
        return vx * f, vy * f, vz * f
    # angle in [pi/2, pi]: axis from the symmetric part R + R^T = 2 c I + 2 (1 - c) a a^T
    angle = math.atan2(s, c)
    d = 1.0 - c
    ax = _sqrt(max((r00 - c) / d, 0.0))
    ay = _sqrt(max((r11 - c) / d, 0.0))
    az = _sqrt(max((r22 - c) / d, 0.0))
    # signs: take the largest component positive, others from the off-diagonals
    if ax >= ay and ax >= az:
        ay = math.copysign(ay, r01 + r10)
        az = math.copysign(az, r02 + r20)
        if vx < 0.0:
            ax, ay, az = -ax, -ay, -az
    elif ay >= az:
        ax = math.copysign(ax, r01 + r10)
        az = math.copysign(az, r12 + r21)
        if vy < 0.0:
            ax, ay, az = -ax, -ay, -az
    else:
        ax = math.copysign(ax, r02 + r20)
        ay = math.copysign(ay, r12 + r21)
        if vz < 0.0:
            ax, ay, az = -ax, -ay, -az
    nrm = _sqrt(ax * ax + ay * ay + az * az)
    return ax * angle / nrm, ay * angle / nrm, az * angle / nrm


def atb3(x, y, rows: int, out) -> None:
    """``out = X^T Y`` (3x3, row-major) for ``X``, ``Y`` of ``rows`` rows of 3,
    row-major flat: ``out[3 a + c] = sum_j x[3 j + a] y[3 j + c]``."""
    for a in range(3):
        for c in range(3):
            acc = 0.0
            for j in range(rows):
                acc += x[3 * j + a] * y[3 * j + c]
            out[3 * a + c] = acc


def congruence3(m, c, c0: int, out, o0: int) -> None:
    """``out[o0:o0+3, o0:o0+3] = M C_b M^T`` with ``C_b = c[c0:c0+3, c0:c0+3]`` (a 3x3 block of a
    covariance turned into another frame; ``m``, ``c``, ``out`` indexable by ``[i, j]``)."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for a in range(3):
                for b in range(3):
                    acc += m[i, a] * c[c0 + a, c0 + b] * m[j, b]
            out[o0 + i, o0 + j] = acc


def inv3_sym(a00, a01, a02, a11, a12, a22):
    """Inverse of the symmetric 3x3 ``[[a00 a01 a02] [a01 a11 a12] [a02 a12 a22]]``
    as its six distinct elements ``(i00, i01, i02, i11, i12, i22)`` (adjugate
    / determinant), or ``None`` when the matrix is not positive definite
    (Sylvester: a leading minor not positive, or not finite)."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    if not (a00 > 0.0 and c22 > 0.0 and det > 0.0) or det == math.inf:
        return None
    inv = 1.0 / det
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    return c00 * inv, c01 * inv, c02 * inv, c11 * inv, c12 * inv, c22 * inv


def quad3_sym(s, x: float, y: float, z: float) -> float:
    """``r^T S r`` for ``r = (x, y, z)`` and a symmetric ``S`` given as the six
    elements ``inv3_sym`` returns."""
    s00, s01, s02, s11, s12, s22 = s
    return (x * (s00 * x + s01 * y + s02 * z) + y * (s01 * x + s11 * y + s12 * z)
            + z * (s02 * x + s12 * y + s22 * z))


def skew_into(v, out) -> None:
    """``out = [v]x`` for a 3-vector ``v`` (``out`` (3, 3), may be a view)."""
    out[0, 0] = 0.0
    out[1, 1] = 0.0
    out[2, 2] = 0.0
    out[0, 1] = -v[2]
    out[0, 2] = v[1]
    out[1, 0] = v[2]
    out[1, 2] = -v[0]
    out[2, 0] = -v[1]
    out[2, 1] = v[0]


def exp_rotvec(wx: float, wy: float, wz: float, out) -> None:
    """``out = exp([w]x)`` (Rodrigues) into a 3x3 buffer indexable ``out[i, j]``.
    An infinite angle (a diverged step) gives NaN, for the caller's finiteness check, not an exception."""
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < 1e-12:
        a = 1.0 - t2 / 6.0
        b = 0.5 - t2 / 24.0
    elif t2 == math.inf:
        a = b = math.nan
    else:
        t = _sqrt(t2)
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    out[0, 0] = 1.0 - b * (wy * wy + wz * wz)
    out[1, 1] = 1.0 - b * (wx * wx + wz * wz)
    out[2, 2] = 1.0 - b * (wx * wx + wy * wy)
    out[0, 1] = b * wx * wy - a * wz
    out[1, 0] = b * wx * wy + a * wz
    out[0, 2] = b * wx * wz + a * wy
    out[2, 0] = b * wx * wz - a * wy
    out[1, 2] = b * wy * wz - a * wx
    out[2, 1] = b * wy * wz + a * wx
