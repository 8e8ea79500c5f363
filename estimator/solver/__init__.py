"""Smoothing a window of knots: Levenberg–Marquardt driven from Python.

    linearize      every factor's rows and Jacobians at every knot (the engine on its
                   threads, the chain rule through the finite differences, batched)
    banded         the block-banded normal equations, the damped step, the marginals
    covariance     honest σ, and the covariance the model's uncertain parameters add
    window         one window solved, its past marginalized into the next window's prior, the
                   backward step
    softness_fit   the model's contact softness fitted to a log's start

Each iteration linearizes every interior knot (MuJoCo's mjd_inverseFD, threaded, the GIL
released), then whitens, robustly weights and chains the rows for all knots at once (numpy).
Every factor sits on three consecutive keys (z_{k−1}, z_k, z_{k+1}), the constant-acceleration
prior on four (dof to dof), so each Levenberg–Marquardt trial is one banded Cholesky, O(T).

Measured on the humanoid (27 dofs, 400 knots a window): GTSAM's elimination per trial cost
as much as the MuJoCo linearization itself (one JacobianFactor per knot built in Python, the
graph cloned per damping); the banded solve costs a tenth of it. Driving the loop from Python
also avoids GTSAM's CustomFactor path, which copies the whole Values on every callback
(../shared/DESIGN.md: 109× slower at 2000 variables).
"""
