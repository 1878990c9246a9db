"""The live view: the Rerun sink that shows a scan as it runs, and its preview images."""
