"""Righetti & Lenzo (2025), "A Combined Dynamic-Kinematic Extended Kalman Filter for Estimating
Vehicle Sideslip Angle", Appl. Sci. 15(3), 1365 (shared/papers/righetti-lenzo2025-dk-ekf.txt):
the DK-EKF (``dk_ekf``) and the paper's two baselines, the dynamic EKF alone (``d_ekf``) and
the kinematic KF alone (``k_kf``), all built from the filters in ``filters``."""
