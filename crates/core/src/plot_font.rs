//! The font every PNG moonhaul draws (learning curves, mission profiles) labels its axes with:
//! a bundled ASCII subset of DejaVu Sans (`assets/fonts/`, licence beside it) through
//! plotters' `ab_glyph` backend, so no system font library is needed. Behind the `plot`
//! feature: nothing onboard draws.

use std::sync::OnceLock;

/// The family name plots ask for; [`register`] binds it to the bundled font.
pub const FAMILY: &str = "sans-serif";

static FONT: &[u8] = include_bytes!("../../../assets/fonts/DejaVuSans-ascii.ttf");

/// Registers the bundled font as [`FAMILY`] (once per process); an error if it is unusable.
pub fn register() -> Result<(), &'static str> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FAMILY, plotters::style::FontStyle::Normal, FONT).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err("the bundled plot font is invalid")
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_bundled_font_registers() {
        assert_eq!(super::register(), Ok(()));
    }
}
