"""Chen, Chen, Cai, Xu (2018), "Estimation of vehicle sideslip angle via pseudo-multisensor
information fusion method", Metrol. Meas. Syst. 25(3) (shared/papers/chen2018-pseudo-
multisensor-fusion.md): three sideslip estimators ("pseudo-sensors") on the same inputs,
``kbe`` (kinematics, Sec. 2.1), ``dbe`` (dynamics, Sec. 2.2) and ``wbe`` (wheel-speed coupling,
Sec. 2.3), fused by the matrix-weighted linear minimum-variance rule of Sec. 3.2 (``fusion``);
the method ``pseudo_fusion`` outputs the fused estimate or one part (the registry's
``pseudo_fusion_kbe``, ``_dbe``, ``_wbe``). All share one state vector (``state.LAYOUT``)."""
