"""Carnier, Corno, Savaresi (2023), "Hybrid Kinematic-Dynamic Sideslip and Friction
Estimation" (shared/papers/carnier-corno-savaresi2023-hybrid-sideslip-friction.md):
``hybrid_friction``, its adaptive observer (``observer``, Sec. 2) and its slip-based friction
classifier (``classifier``, Sec. 3)."""
