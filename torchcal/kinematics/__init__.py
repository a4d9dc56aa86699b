"""Robot models, the differentiable error layer, forward kinematics, Jacobians and IK."""
