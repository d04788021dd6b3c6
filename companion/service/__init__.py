"""The companion service: the asyncio pipeline from camera to setpoints (see app.py)."""
