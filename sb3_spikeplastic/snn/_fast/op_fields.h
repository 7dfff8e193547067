// Named structures of tensors that travel through an op's schema as one Tensor?[] or Tensor[] (srm_interval.cpp).
//
// A TORCH_LIBRARY schema is positional, so a struct passed to or returned from an op needs an order for its tensors.
// Each such struct lists its fields once, in a static fields() of (name, member) pairs; from_list, to_list and
// field_names read that list and nothing else, so it is the only place on this side that defines the order. The
// Python side mirrors each struct as a NamedTuple of the same field names (sb3_spikeplastic/snn/_fast/interval.py),
// and the op srm_interval_fields returns field_names, so that a test compares the two.
#pragma once

#include <ATen/core/List.h>
#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <optional>
#include <string>
#include <vector>

namespace sb3_spikeplastic_fast {

template <typename S>
struct TensorField {
  const char* name;
  at::Tensor S::*member;
};

template <typename S>
using TensorFields = std::vector<TensorField<S>>;

// The struct S from an op's Tensor?[] argument; a None entry is an undefined tensor.
template <typename S>
S from_list(const c10::List<std::optional<at::Tensor>>& list) {
  const auto& fields = S::fields();
  TORCH_CHECK(list.size() == fields.size(), S::kName, ": ", fields.size(), " tensors expected, got ", list.size());
  S s;
  for (size_t i = 0; i < fields.size(); ++i) {
    const std::optional<at::Tensor> t = list.get(i);
    if (t.has_value()) s.*(fields[i].member) = *t;
  }
  return s;
}

// S as an op's Tensor[] result; an undefined tensor reaches Python as None.
template <typename S>
std::vector<at::Tensor> to_list(const S& s) {
  std::vector<at::Tensor> list;
  list.reserve(S::fields().size());
  for (const auto& field : S::fields()) list.push_back(s.*(field.member));
  return list;
}

template <typename S>
std::vector<std::string> field_names() {
  std::vector<std::string> names;
  for (const auto& field : S::fields()) names.emplace_back(field.name);
  return names;
}

}  // namespace sb3_spikeplastic_fast
