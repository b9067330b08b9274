//! The live view's page: one self-contained HTML document (inline CSS and
//! JavaScript, no external script, font, stylesheet or CDN: benches are often
//! offline). It connects to `api/events` (server-sent events) and redraws from the
//! pushed JSON; plots are inline SVG drawn by its own small script (no chart
//! library). The token of a non-loopback view is taken from the page's own URL and
//! passed on with every request.

/// The page (`GET /`).
pub const PAGE: &str = include_str!("page.html");

#[cfg(test)]
mod tests {
    use super::PAGE;

    #[test]
    fn the_page_loads_nothing_from_elsewhere() {
        for needle in [
            "http://",
            "https://",
            "//cdn",
            "@import",
            "<link",
            "src=\"http",
        ] {
            let hits: Vec<&str> = PAGE
                .lines()
                .filter(|l| l.contains(needle) && !l.contains("www.w3.org/2000/svg"))
                .collect();
            assert!(hits.is_empty(), "{needle}: {hits:?}");
        }
        assert!(PAGE.contains("new EventSource(\"api/events\""));
    }
}
