"""Synthetic LiDAR worlds with revisits: training and evaluation data without KITTI.

The data path, one module per step:

    streets  → a perturbed street grid and its districts
    terrain  → gentle hills everything stands on
    world    → buildings, street furniture, kerbs and markings: one static mesh
    dynamics → parked cars, traffic and pedestrians as functions of time
    trajectory → a route with same- and opposite-direction revisits, driven at 10 Hz
    lidar    → Embree ray casting of a spinning multi-beam sensor
    generate → KITTI-layout output, overlap ground truth, manifest and map

Needs trimesh/embreex/scipy (the ``train`` extra); never imports torch.
"""
