"""Universal Robots arms: the :class:`~.robot.URRobot` driver and the wire clients it uses.

``robot`` (the facade) over ``motion`` (commands, control child's supervisor) over ``stream``
(the receive child's supervisor); the children are ``receive_child`` and ``control``, sharing
``process``; ``receive`` (native RTDE client), ``rtde_wire`` (RTDE codec) and ``primary`` (the
factory kinematics) speak the controller's protocols.
"""
