"""medc_bringup: starting and measuring the whole MEDC system.

``launcher`` (medc-launch: simulator, agent nodes and bridge from one YAML config), ``demo``
(medc-demo: the paper's time sequence end to end), ``bench`` (medc-bench ros) and ``gas``
(medc-gas-report: the contracts' gas next to the paper's table, an offline measurement).
"""
