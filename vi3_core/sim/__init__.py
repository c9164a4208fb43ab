"""Simulation with exact ground truth: analytic drone trajectories, IMU synthesis, noisy 3DFM-like poses."""
