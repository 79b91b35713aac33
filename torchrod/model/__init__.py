"""The forward model in torch: a clamped rod under point forces, integrated in the body frame from the free tip,
differentiable and batched.

``body_frame`` (simulate, grating_curvature: the march with its discrete adjoint, :mod:`.nystrom`), ``precurved``
(rods with intrinsic curvature), ``shape`` (position and frames), ``global_bvp`` (the independent global-frame
reference and the paper's baselines). The estimator's own models are the kernels of :mod:`torchrod.kernels`.
"""
