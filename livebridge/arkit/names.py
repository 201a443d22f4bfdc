"""The names of the Live Link Face values, in the order they travel.

The first 52 are Apple's ARKit face blendshapes in the order of ``ARFaceAnchor.BlendShapeLocation`` as
Unreal's ``EARFaceBlendShape`` enumerates them (the order the Live Link Face app sends them; see
:mod:`livebridge.arkit.packet` for the sources), spelt as ARKit spells them (camelCase). Then nine rotations:
the head's yaw, pitch and roll and each eye's yaw, pitch and roll.
"""

from __future__ import annotations

ARKIT_NAMES = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight",
    "eyeWideRight",
    "jawForward", "jawLeft", "jawRight", "jawOpen",
    "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)
ROTATION_NAMES = ("headYaw", "headPitch", "headRoll", "leftEyeYaw", "leftEyePitch", "leftEyeRoll",
                  "rightEyeYaw", "rightEyePitch", "rightEyeRoll")
LIVELINK_NAMES = ARKIT_NAMES + ROTATION_NAMES
N_BLENDSHAPES = len(ARKIT_NAMES)  # 52
N_VALUES = len(LIVELINK_NAMES)  # 61
HEAD_ROTATION = slice(N_BLENDSHAPES, N_BLENDSHAPES + 3)  # yaw, pitch, roll
ARKIT_INDEX = {name: k for k, name in enumerate(ARKIT_NAMES)}
