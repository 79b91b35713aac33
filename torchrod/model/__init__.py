"""The forward model: a clamped rod under point forces, integrated in the body frame from the free tip.

``body_frame`` (simulate, grating_curvature: primal march with its discrete adjoint, :mod:`.nystrom`),
``sensitivity`` (the same march with forward tangents: curvature and its Jacobian for estimation), ``shape``
(position and frames), ``global_bvp`` (the independent global-frame reference and the paper's baselines).
"""
