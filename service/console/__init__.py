"""The browser console: its static pages, scripts and styles (static/, three.js vendored in
static/vendor/ by scripts/vendor-three.sh) and the documents it reads beyond the API's JSON
(documents.py); served by service/api/routers/console.py."""
