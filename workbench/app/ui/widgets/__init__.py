"""Small pieces every feature of the server uses: colours, Markdown escaping, page CSS, telling our own GUI writes
from the user's, and throttled redraws."""
