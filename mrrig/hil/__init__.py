"""Real-time hybrid simulation numerics (spec/hil.md): the numerical substructures (a quarter car
on an ISO 8608 road, a shear building under ground motion), the semi-active laws, the actuator
delay compensation, the tracking metrics J1-J3 and the all-numerical reference.

Pure numerics: nothing here knows CAN, Zenoh or Rerun. Every stepping class advances one sensor
frame per call, so the daemon's loop and the reference run the same code.
"""
