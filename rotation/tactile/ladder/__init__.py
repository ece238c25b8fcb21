"""The information ladder of `rotate touch-report`: how much of the object's friction, mass and centre of mass,
and of each fingertip's force and slip, each stage of the touch path still holds."""
