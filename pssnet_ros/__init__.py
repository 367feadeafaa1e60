"""Thin ROS 2 layer over pssnet_core: message conversions, parameters, the completion node and its demo."""
