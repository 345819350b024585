"""Readers and writers of the project's file formats, and the output policy (:mod:`.outputs`)."""
