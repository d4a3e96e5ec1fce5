"""Test harness: a headless Chromium for screenshots and for running shaders."""
