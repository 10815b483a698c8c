"""The venue console (`rig console`): one page in the browser that runs the rig (docs/console.md)."""
