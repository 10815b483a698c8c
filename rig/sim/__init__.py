"""The simulator as the rest of rig sees it, besides the simulated devices themselves.

`rig` reaches the simulator only through here, the simulated devices (the `sim://` camera backend
rig/cameras/sim.py, the `sim://` trigger board rig/boards/sim.py, the ground-truth source
rig/truth/simulator.py) and the simulator's own commands, so that the simulator stays out of the
real-camera path (tests/test_layering.py):
- `clock.py`: simulated time zero, shared by the cameras and the board of one rig;
- `rig_config.py`: the configuration of a simulated rig (`rig config init --sim`, `rig demo`);
- `options.py`: the check of a config's `[sim]` tables;
- `calibration.py`: a simulated calibration session for `rig calibrate capture`.
"""
