//! The live view's page: one self-contained HTML document (inline CSS and
//! JavaScript, no external script, font, stylesheet or CDN: benches are often
//! offline). It connects to `api/events` (server-sent events) and redraws from the
//! pushed JSON; plots are inline SVG drawn by its own small script (no chart
//! library). The token of a non-loopback view is taken from the page's own URL and
//! passed on with every request; the view's token is also written into the page
//! ([`page`]) for its Stop button, which sends it as `X-Tactbench-Token`.

/// The page's template: [`page`] fills in [`TOKEN_SLOT`].
pub const PAGE: &str = include_str!("page.html");

/// Where the view's token goes in [`PAGE`] (the `content` of a `<meta>`).
pub const TOKEN_SLOT: &str = "{{TACTBENCH_TOKEN}}";

/// The page as served (`GET /`), carrying the view's token (hex: nothing to escape).
pub fn page(token: &str) -> String {
    PAGE.replacen(TOKEN_SLOT, token, 1)
}

#[cfg(test)]
mod tests {
    use super::{page, PAGE, TOKEN_SLOT};

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

    #[test]
    fn the_served_page_carries_the_token_once_and_no_template_slot() {
        assert_eq!(PAGE.matches(TOKEN_SLOT).count(), 1);
        let p = page("00ff00ff00ff00ff00ff00ff00ff00ff");
        assert!(!p.contains(TOKEN_SLOT));
        assert!(p.contains(
            r#"<meta name="tactbench-token" content="00ff00ff00ff00ff00ff00ff00ff00ff">"#
        ));
    }
}
