"""pyrtu bridge: poller points to MQTT (issue 19)."""
