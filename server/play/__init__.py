"""One browser tab's session: the session and its manager, the play scheduler, the compiled play steps, the
renderer, and the gallery's part of a tab."""
