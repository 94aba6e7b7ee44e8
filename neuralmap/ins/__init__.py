"""GNSS/MEMS-IMU loosely coupled navigation, batched over N runs (SEEDS 003).

WGS-84 Earth model and a strapdown mechanisation in the north-east-down (NED) frame,
a land-vehicle trajectory generator with exact IMU outputs, a MEMS IMU error model, GNSS
simulation with urban effects and quality records, and the 15-state ψ-angle error-state
EKF with lever-arm position/velocity updates on `neuralmap.filters.BatchedEKF`.
"""
