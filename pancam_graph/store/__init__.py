"""The project's own folders: results folders (written atomically, read back), checkpoints for
--resume, and observation folders (the format an external front-end writes for the back-end)."""
