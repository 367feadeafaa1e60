"""Development tools of the completion node: the test harness, the synthetic camera and the demo (not for robots)."""
