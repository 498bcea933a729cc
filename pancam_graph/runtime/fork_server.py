"""Imported last by the fork server (processes.PRELOAD), once everything a worker runs is
imported: from here on the fork server only forks, so it hands back the resident pages of the
code it read while importing (processes.release_library_pages). A forked worker reads the
code it runs from the page cache, as it would anyway. Nothing
else imports this module."""

from .processes import release_library_pages

release_library_pages()
