"""The registered systems: one line each. A system is a package here whose __init__.py defines SYSTEM
(a wrenorm.system.System); see README, "Adding a system"."""

SYSTEMS = (
    "wrenorm.tasks.pd",
    "wrenorm.tasks.rope",
    "wrenorm.tasks.swimmer",
)
