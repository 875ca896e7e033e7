"""The capture: pattern files and the plan's pattern sets, the capture plan, the session folder (one owner:
twin.capture.session) and the device backends that show patterns and grab frames (twin.capture.backends)."""
