"""physics: the paper's forward and inverse dynamics with contacts, on MuJoCo.

Todorov (2014), "Convex and analytically-invertible dynamics with contacts and constraints".
Phase I (kinematics, inertia, collision, Jacobians) comes from MuJoCo; Phase II (impulses)
is written here as the *reference* path and mirrored by MuJoCo's C engine as the *native* path.
See `physics/NOTATION.md` for the paper-symbol -> code -> MuJoCo-field table.
"""
