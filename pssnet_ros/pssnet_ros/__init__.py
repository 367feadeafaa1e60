"""Thin ROS 2 layer over pssnet_core, what a robot runs: message conversions, parameters, the completion node,
`pssnet bag`, and the clean-up of stale Fast DDS shared memory."""
