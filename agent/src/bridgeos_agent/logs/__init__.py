"""Component logs on the robot: capture (``capture``), the on-disk rings (``ring``), shipping (``shipper``).

``service.ComponentLogService`` ties them to a robot's runtime and session.
"""
