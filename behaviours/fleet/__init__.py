"""The factory fleet of seed paper 000 (ROS-JADE transport agents), on beehave's agent layer.

Kobuki ATVs carry material from a depot to machines that consume it; machines order it by
contract net; charging stations lease one place each; speed zones set each robot's
``max_speed_mps`` parameter as it drives. Every part is an agent in its own process:

=====================================  ===================================================
``behaviours.fleet.atv``               the ATV's behaviours: ``work`` (bids for and does
                                       transport orders), ``charge`` (negotiates a station)
``behaviours.fleet.zones``             the ATV's speed-zone logic (low level)
``behaviours.fleet.machine``           a machine agent (``python -m …machine NAME``)
``behaviours.fleet.station``           a charging-station agent (``… station NAME``)
``behaviours.fleet.mission``           the mission controller: one state machine per order
``behaviours.demos.fleet``             ``beehave fleet``: all of it, checked in the physics
=====================================  ===================================================

Schemas on the wire (std_msgs/String, JSON) are in ``docs/fleet.md``.
"""
