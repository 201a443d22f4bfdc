"""ARKit blendshapes in and out: the Live Link Face wire format, a UDP receiver, ARKit-named shape sets, and
the solve that turns ARKit weights into muscle contractions (an iPhone as a markerless capture source)."""
