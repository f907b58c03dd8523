"""Building blocks every method is made of: state layouts, input reading, filters, kinematics,
tyres, Kalman algebra, outputs and vehicle checks. Kernels here are numba functions on
scalars and the caller's state vector; none allocates."""
