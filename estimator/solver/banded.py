"""The normal equations of a window, block-banded by key, and their Levenberg–Marquardt step.

Every factor sits on three consecutive keys (z_{k−1}, z_k, z_{k+1}), the constant-acceleration
prior on four (dof to dof), so JᵀJ is block-banded (bandwidth 2 or 3 keys), summed straight
into key blocks over the columns each factor reaches: each trial is one banded Cholesky
(LAPACK pbtrf through scipy), O(T); its marginal covariances come from the same factor by
selected inversion (`banded_inverse_blocks`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from estimator.factors import bias_walk
from estimator.factors.base import Block
from estimator.solver.linearize import THREADS, Linearizer, z_columns
from physics.knots import INLINE_KNOTS, chunks

LAMBDA_MIN = 1e-9  # Levenberg–Marquardt's least damping, and its first


LAMBDA_REJECTED = 1e-5  # the least damping after a rejected step


MARGINAL_REGULARIZER = 1e-14  # on the unit diagonal of S H S (`BandedSystem.marginal_std`)


@dataclass
class BandedSystem:
    """JᵀJ dx = −Jᵀr of a window, by blocks of keys: H_kk = diag[k] (T, nz, nz),
    H_{k+d, k} = lower[d − 1][k] for d = 1 … span − 1; g = Jᵀr (T, nz)."""

    diag: np.ndarray
    lower: list[np.ndarray]
    g: np.ndarray

    @classmethod
    def of(
        cls,
        blocks: list[Block],
        lin: Linearizer,
        bias: np.ndarray,
        qpos: np.ndarray | None = None,
        until: int | None = None,
        rows: range | None = None,
        walk: range | None = None,
        bias_prior: bool | None = None,
    ) -> BandedSystem:
        """The system of `lin.linearize`'s blocks (and the bias prior and walk, and the
        marginal prior at qpos). until: only the factors on keys ≤ until — the rows of knots
        k ≤ until − span + 2 and the walk steps to keys ≤ until — what a window's past says
        before its keys ≤ until are marginalized (`marginal_prior`).
        rows, walk: only the rows of these knots and the walk steps k → k + 1 of these k (an
        incremental update's parts: `incremental`); bias_prior: the bias prior on b_0
        (default: without a marginal prior)."""
        p = lin.problem
        if until is not None:
            last_row = until - lin.span + 2  # knot of the last row kept: it reaches key `until`
            rows = range(1, last_row + 1)
            walk = range(0, min(p.T - 1, last_row))
        if rows is not None:
            knot = np.arange(p.T - 2) + 1
            keep = ((knot >= rows.start) & (knot < rows.stop))[:, None]
            blocks = [
                replace(
                    b,
                    r=b.r * keep,
                    J=None if b.J is None else b.J * keep.reshape(-1, *[1] * (b.J.ndim - 1)),
                    J_bias=None if b.J_bias is None else b.J_bias * keep[:, :, None],
                )
                for b in blocks
            ]
        T, nz, span = p.T, p.nz, lin.span
        K = T - 2
        n_rows = K if rows is None else max(0, min(K, rows.stop - 1))
        # Knot row i (knot k = i + 1) reaches keys i + a, a = 0 … span − 1. Each factor's
        # Jacobian is split by key into runs of consecutive columns, (a, columns in J,
        # columns in z_{i+a}) (slices: fancy indexing is 5× slower). The sensors' blocks, a
        # few rows each, are stacked into one over the union of their columns.
        dofwise = [(b.r, b.J) for b in blocks if b.dofwise and b.J is not None]
        groups = [[b] for b in blocks if not (b.dofwise or b.sensor)]
        groups.append([b for b in blocks if b.sensor])
        parts = []  # (r, [(J, its columns in the union)], number of columns, runs)
        for group in groups:
            reach = [z_columns(p, b) for b in group]
            if len(reach) == 1:  # its own columns, in their order
                cols = reach[0][1]
            else:
                cols = np.unique(np.concatenate([c for _, c in reach] or [np.zeros(0, int)]))
            if not len(cols):  # (rows with no measurement in this window)
                continue
            starts = np.flatnonzero((np.diff(cols, prepend=-2) != 1) | (cols % nz == 0))
            runs = [
                (cols[i] // nz, slice(i, j), slice(cols[i] % nz, cols[i] % nz + j - i))
                for i, j in zip(starts, [*starts[1:], len(cols)], strict=True)
            ]
            r = np.concatenate([b.r for b in group], axis=1)
            parts.append((r, [(J, np.searchsorted(cols, c)) for J, c in reach], len(cols), runs))
        # the priors' rows reach one dof (or one rotation's 3) per key: JᵀJ by dof groups
        vec = lin.vector_dofs

        def products(keys: range) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
            """The (diag, lower, g) blocks of `keys` (zero elsewhere), in their own arrays
            (threads). Every block is summed in the same order whatever the split of the keys
            (the rows that reach it, factor by factor): the result does not depend on the
            number of threads."""
            diag = np.zeros((T, nz, nz))
            lower = [np.zeros((T - d, nz, nz)) for d in range(1, span)]
            g = np.zeros((T, nz))
            H = [diag, *lower]  # H[a − b][key of b]: H_{k+a−b, k}

            def reaching(off: int, stop: int) -> tuple[int, int]:
                """The rows i < stop whose key i + off is one of `keys`."""
                i0 = max(0, keys.start - off)
                return i0, max(i0, min(stop, keys.stop - off))

            lo = max(0, keys.start - span + 1)  # every row that reaches one of the keys
            hi = max(lo, min(keys.stop, n_rows))
            for r, reach, n_cols, runs in parts:
                rc = r[lo:hi]
                if len(reach) == 1:
                    Jc = reach[0][0][lo:hi]
                else:
                    Jc = np.zeros((hi - lo, r.shape[1], n_cols))
                    row = 0
                    for J, at in reach:
                        Jc[:, row : row + J.shape[1], at] = J[lo:hi]
                        row += J.shape[1]
                for a, in_a, z_a in runs:
                    Ja = Jc[:, :, in_a]
                    i0, i1 = reaching(a, hi)
                    i0 = max(i0, lo)
                    if i1 > i0:
                        sel = slice(i0 - lo, i1 - lo)
                        g[i0 + a : i1 + a, z_a] += np.einsum("kmc,km->kc", Ja[sel], rc[sel])
                    for b, in_b, z_b in runs:
                        i0, i1 = reaching(b, hi)
                        i0 = max(i0, lo)
                        if b <= a and i1 > i0:
                            sel = slice(i0 - lo, i1 - lo)
                            H[a - b][i0 + b : i1 + b, z_a, z_b] += (
                                Ja[sel].transpose(0, 2, 1) @ Jc[sel][:, :, in_b]
                            )
            for r, C in dofwise:
                n = C.shape[1]  # keys reached (the prior 3, the jerk prior 4)
                # rows reaching key i + a ≤ T − 1 (the jerk prior's last row, zero, reaches T)
                last = [min(n_rows, T - a) for a in range(n)]
                for a in range(n):
                    i0, i1 = reaching(a, last[a])
                    g[i0 + a : i1 + a, vec] += C[i0:i1, a, vec, 0] * r[i0:i1, vec]
                    for b in range(a + 1):
                        i0, i1 = reaching(b, last[a])
                        diagonal = H[a - b].reshape(-1, nz * nz)[:, :: nz + 1]  # a view
                        diagonal[i0 + b : i1 + b, vec] += C[i0:i1, a, vec, 0] * C[i0:i1, b, vec, 0]
                for d in lin.rotation_dofs:  # the 3 rows of a rotation on its 3 columns
                    rot = slice(d, d + 3)
                    for a in range(n):
                        i0, i1 = reaching(a, last[a])
                        JrT = C[i0:i1, a, rot].transpose(0, 2, 1)
                        g[i0 + a : i1 + a, rot] += (JrT @ r[i0:i1, rot, None])[:, :, 0]
                        for b in range(a + 1):
                            i0, i1 = reaching(b, last[a])
                            JrT = C[i0:i1, a, rot].transpose(0, 2, 1)
                            H[a - b][i0 + b : i1 + b, rot, rot] += JrT @ C[i0:i1, b, rot]
            return diag, lower, g

        if T <= INLINE_KNOTS:
            shares = [products(range(T))]
        else:
            shares = list(lin.pool.map(products, chunks(0, T, THREADS)))
        diag, lower, g = shares[0]
        for more_diag, more_lower, more_g in shares[1:]:
            diag += more_diag
            g += more_g
            for mine, more in zip(lower, more_lower, strict=True):
                mine += more
        if p.nb:  # (a marginal prior holds b_0 already) the steps k → k + 1 to keys ≤ the
            # last kept row's knot, with `until`
            steps = range(0, T - 1) if walk is None else walk
            with_prior = lin.prior is None if bias_prior is None else bias_prior
            bias_walk.add_normal_equations(
                p, bias, diag, lower[0], g, with_prior, min(steps.stop, T - 1), steps.start
            )
        if lin.prior is not None:  # ½ eᵀΛe on the first keys: H += Λ, g += Λe
            assert qpos is not None, "a marginal prior needs the window's qpos"
            prior = lin.prior
            Lam = prior.info.reshape(prior.keys, nz, prior.keys, nz)
            Le = (prior.info @ prior.error(p.model, qpos, bias)).reshape(prior.keys, nz)
            for i in range(prior.keys):
                g[i] += Le[i]
                diag[i] += Lam[i, :, i]
                for j in range(i):
                    lower[i - j - 1][j] += Lam[i, :, j]
        return cls(diag, lower, g)

    def marginal_std(self, nv: int, warnings: list[str], keys: range | None = None) -> np.ndarray:
        """(T, nv) marginal standard deviations of x_k at `keys` (default: all; NaN at the
        others): the diagonal of H⁻¹ = S (S H S)⁻¹ S (S = diag(H)^−½) by a banded Cholesky
        of the scaled system and the selected inverse of its band (`banded_inverse_blocks`).

        Contact directions make JᵀJ stiff (≈1e12–1e17) beside weakly observed ones (1e6), and
        S H S has eigenvalues far below 1: an accelerometer at every knot puts ≈4e14 on the
        diagonal where the mocap knows the position as a whole to ≈1e6 (an eigenvalue ≈2e-9);
        a free object's tilt in a gripper at h = 0.5 ms reaches ≈5e-12. GTSAM's Marginals
        declared that system indeterminate below a regularizer of 1e-8 on the unit diagonal,
        which halved the position σ of every floating base. MARGINAL_REGULARIZER only keeps
        the directions nothing observes finite (there σ comes out huge, as it should)."""
        T, nz, _ = self.diag.shape
        std = np.full((T, nv), np.nan)
        s, ab = self.scaled_band()
        try:
            L = self.factor(ab, MARGINAL_REGULARIZER)
        except np.linalg.LinAlgError as err:
            warnings.append(f"covariances unavailable ({err}); qpos_std is NaN")
            return std
        return factor_std(L, s, nz, nv, range(T) if keys is None else keys)

    @staticmethod
    def factor(ab: np.ndarray, lam: float) -> np.ndarray:
        """The banded Cholesky factor L of S H S + λ I (`scaled_band`'s ab), LAPACK's lower
        storage; raises LinAlgError when it is not positive definite."""
        damped = ab.copy(order="F")
        damped[0] += lam
        return scipy.linalg.cholesky_banded(
            damped, overwrite_ab=True, lower=True, check_finite=False
        )

    @staticmethod
    def solve(L: np.ndarray, s: np.ndarray, G: np.ndarray) -> np.ndarray:
        """−(H + λD)⁻¹ g for each column g of G (T, nz, m) from that factor: (T, nz, m)."""
        rhs = -s[:, None] * G.reshape(-1, G.shape[-1])
        y = scipy.linalg.cho_solve_banded((L, True), rhs, check_finite=False)
        return (s[:, None] * y).reshape(G.shape)

    def reversed(self) -> BandedSystem:
        """The same system with its keys in reverse order (key k is key T − 1 − k):
        `marginal_std` goes from the last key down, so the first keys' σ cost only their
        own keys in the reversed system. H'_{k+d, k} = H_{T−1−k, T−1−k−d} = (H_{T−1−k−d+d,
        T−1−k−d})ᵀ, i.e. lower'[d] = lower[d] reversed and transposed."""
        return BandedSystem(
            self.diag[::-1].copy(),
            [lo[::-1].transpose(0, 2, 1).copy() for lo in self.lower],
            self.g[::-1].copy(),
        )

    def scaled_band(self) -> tuple[np.ndarray, np.ndarray]:
        """Marquardt scaling s = diag(H)^−½ and the lower band of S H S in LAPACK storage
        (ab[i − j, j] = (S H S)_ij), unit diagonal.

        The band is as wide as the farthest coupling: keys span − 1 apart couple only through
        the jerk prior, dof to dof (a rotation's 3 to its 3), so its rows end there: 3 nz + 3
        rows instead of 4 nz (the banded Cholesky's cost goes with the band's square)."""
        T, nz, _ = self.diag.shape
        d = np.einsum("kii->ki", self.diag).reshape(-1)
        s = 1.0 / np.sqrt(d + 1e-12 * max(float(d.max()), 1.0))
        S = s.reshape(T, nz)
        span = len(self.lower) + 1
        rows, cols = np.nonzero(np.any(self.lower[-1] != 0, axis=0))
        kd = (span - 1) * nz + int(np.max(rows - cols, initial=-1))  # the farthest nonzero
        # LAPACK's ab[i − j, j] = H_ij: key k's column c holds H_{k+o, k}[r, c] at
        # i − j = o nz + r − c, written through a skewed view of M[k, c, nz + (i − j)] (the
        # padding nz on each side takes the diagonal block's upper half and the zeros past kd)
        M = np.zeros((T, nz, nz + kd + 1 + nz))
        st = M.strides
        for offset, blocks in enumerate([self.diag, *self.lower]):
            n = len(blocks)
            skewed = np.lib.stride_tricks.as_strided(
                M[:n, :, (offset + 1) * nz :],
                shape=(n, nz, nz),
                strides=(st[0], st[1] - st[2], st[2]),
            )  # skewed[k, c, r] = M[k, c, nz + offset·nz + r − c]
            skewed[...] = (S[offset : offset + n, :, None] * blocks * S[:n, None, :]).transpose(
                0, 2, 1
            )
        # in Fortran order, as LAPACK reads it (scipy would copy it otherwise)
        ab = M[:, :, nz : nz + kd + 1].reshape(T * nz, kd + 1).T
        return s, ab

    def predicted_decrease(self, s: np.ndarray, lam: float, dx: np.ndarray) -> float:
        """The quadratic model's cost decrease −gᵀdx − ½dxᵀH dx at the damped step dx, which
        solves (H + λD) dx = −g with D = s⁻²: ½(−gᵀdx + λ dxᵀD dx)."""
        d = dx.reshape(-1)
        return 0.5 * float(-self.g.reshape(-1) @ d + lam * np.sum(np.square(d / s)))

    def damped_step(self, s: np.ndarray, ab: np.ndarray, lam: float) -> np.ndarray:
        """argmin ‖J dx + r‖² + λ Σ diag(JᵀJ) dx² → dx (T, nz); raises LinAlgError when the
        damped system is not positive definite."""
        return self.damped_steps(s, ab, lam, self.g[..., None])[..., 0]

    def damped_steps(self, s: np.ndarray, ab: np.ndarray, lam: float, G: np.ndarray) -> np.ndarray:
        """The damped steps −(H + λD)⁻¹ g for each column g of G (T, nz, m), one
        factorization: (T, nz, m)."""
        return self.solve(self.factor(ab, lam), s, G)


def factor_std(L: np.ndarray, s: np.ndarray, nz: int, nv: int, keys: range) -> np.ndarray:
    """(T, nv) marginal σ of x_k at `keys` (NaN at the others) from the factor L of the scaled
    system (`BandedSystem.factor`): the diagonal blocks of its inverse by selected inversion
    from the last key down to keys.start (`banded_inverse_blocks`)."""
    T = L.shape[1] // nz
    std = np.full((T, nv), np.nan)
    if not len(keys):
        return std
    Z = banded_inverse_blocks(L, nz, keys.start)
    variance = np.einsum("kii->ki", Z)[:, :nv] * s.reshape(T, nz)[keys.start :, :nv] ** 2
    chosen = np.asarray(keys, dtype=int)
    std[chosen] = np.sqrt(np.clip(variance[chosen - keys.start], 0.0, None))
    return std


def front_std(L: np.ndarray, s: np.ndarray, nz: int, nv: int, keys: range) -> np.ndarray:
    """The same at a window's first keys without traversing it from the end: Σ_kk =
    (L⁻¹E_k)ᵀ(L⁻¹E_k), E_k key k's columns of the identity; L⁻¹E_k is zero above key k,
    and below it one banded triangular solve (LAPACK tbtrs) on L's trailing part."""
    T = L.shape[1] // nz
    std = np.full((T, nv), np.nan)
    for k in keys:
        E = np.zeros((L.shape[1] - k * nz, nv))
        E[:nv] = np.eye(nv)
        Y, info = scipy.linalg.lapack.dtbtrs(L[:, k * nz :], E, uplo="L")
        if info != 0:
            continue
        std[k] = np.sqrt(np.einsum("ji,ji->i", Y, Y)) * s[k * nz : k * nz + nv]
    return std


def banded_inverse_blocks(L: np.ndarray, nz: int, first: int = 0) -> np.ndarray:
    """The diagonal blocks Z_kk (T − first, nz, nz) of A⁻¹ for A = L Lᵀ, L lower banded in
    LAPACK storage (L[d, j] = L_{j+d, j}), keys of nz unknowns, without forming A⁻¹: the
    selected inversion (Takahashi's recurrence) from Lᵀ Z = L⁻¹, key k from the last down,

        Z_{k, k+1:k+m} = −L_kk⁻ᵀ B_kᵀ Z_{k+1:k+m, k+1:k+m},
        Z_kk = L_kk⁻ᵀ (L_kk⁻¹ − B_kᵀ Z_{k, k+1:k+m}ᵀ),

    with B_k the rows of L below L_kk in key k's columns and m keys its band reaches; Z is
    needed only within the band, held as a rolling window of m + 1 keys."""
    kd, N = L.shape[0] - 1, L.shape[1]
    T = N // nz
    m = -(-kd // nz)  # keys below the diagonal block a column reaches
    w = (m + 1) * nz
    # C[k, t, c] = L[k nz + t, k nz + c]: key k's columns, rows k nz … k nz + w − 1
    t, c = np.arange(w)[:, None], np.arange(nz)[None, :]
    d = t - c
    inside = (d >= 0) & (d <= kd)
    cols = np.arange(first, T)[:, None, None] * nz + c[None]  # (the keys asked for only)
    rows = cols + d[None]
    C = np.where(
        inside[None] & (rows < N), L[np.clip(d, 0, kd)[None], np.minimum(cols, N - 1)], 0.0
    )
    out = np.empty((T - first, nz, nz))
    W = np.zeros((w, w))  # Z over keys k … k + m (rows beyond the last key stay 0)
    for k in range(T - 1, first - 1, -1):
        Lkk, B = C[k - first, :nz], C[k - first, nz:]
        sub = W[: w - nz, : w - nz]  # keys k + 1 … k + m, the previous window's first m
        X = scipy.linalg.solve_triangular(Lkk, B.T @ sub, lower=True, trans="T")
        inv_Lkk = scipy.linalg.solve_triangular(Lkk, np.eye(nz), lower=True)
        Zkk = scipy.linalg.solve_triangular(Lkk, inv_Lkk + B.T @ X.T, lower=True, trans="T")
        Zkk = 0.5 * (Zkk + Zkk.T)
        new = np.empty((w, w))
        new[nz:, nz:] = sub
        new[:nz, nz:] = -X
        new[nz:, :nz] = -X.T
        new[:nz, :nz] = Zkk
        W = new
        out[k - first] = Zkk
    return out
