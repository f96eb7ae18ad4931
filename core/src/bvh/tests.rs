use super::*;

#[test]
fn kernel_names_parse_and_unknown_ones_are_refused() {
    for k in Kernel::ALL {
        assert_eq!(Kernel::parse(k.name()), Ok(k));
    }
    assert_eq!(Kernel::parse(" AVX2 "), Ok(Kernel::Avx2));
    let e = Kernel::parse("avx512").unwrap_err();
    assert!(e.contains("avx2, sse or scalar"), "{e}");
    assert!(Kernel::Scalar.supported());
    assert!(Kernel::detect().supported());
}
