"""medc_common: what every MEDC node shares, so that none of them needs another's package.

``contract`` (topic names, QoS, frames, agent ids, grid <-> map conversion), ``params`` (declaring
parameters), ``executors`` (the executor and the life of a console-script node) and ``ros_env``
(making the colcon-built medc_interfaces importable).
"""
