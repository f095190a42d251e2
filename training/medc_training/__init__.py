"""MEDC offline training: environments, multi-agent PPO, MEDC, baselines, policy bundles.

This package never imports rclpy or web3: the ROS nodes and the registry depend on it,
never the other way round.
"""

__version__ = "0.1.0"
